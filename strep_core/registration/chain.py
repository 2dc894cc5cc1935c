"""The incremental chain: each frame registered to the previous one (or to a local map of the
previous ones), from the initial guess's relative motion; the pose of frame k is the chain of
the pairs up to k. Used by ``icp``, by the pose graph's odometry edges and by the warm starts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from strep_core import geometry as g
from strep_core.errors import RegistrationError
from strep_core.registration.clouds import from_se3, open3d_quiet, prepare_frame, project_planar, transform_cloud
from strep_core.registration.pairwise import PairResult, correspondences, icp_pair
from strep_core.registration.params import RegistrationParams
from strep_core.sequence import Sequence

if TYPE_CHECKING:  # pragma: no cover
    from strep_core._open3d import o3d


@dataclass
class IncrementalResult:
    """Output of `incremental_icp`.

    Attributes:
        poses: ``(K, D+1, D+1)`` local -> world poses, ``poses[0]`` = the initial guess's.
        pairs: ``K-1`` results; ``pairs[k-1]`` registers frame k to frame k-1 (or to its map).
        clouds: the prepared Open3D clouds (downsampled, with normals), for reuse.
        seconds: time spent in registration.
    """

    poses: np.ndarray
    pairs: list[PairResult]
    clouds: list[Any] = field(default_factory=list)
    seconds: float = 0.0


def prepare_frames(seq: Sequence, params: RegistrationParams) -> list[o3d.geometry.PointCloud]:
    """`prepare_frame` for every frame of ``seq`` (uses the sequence's sensor origins)."""
    assert seq.origins is not None
    return [prepare_frame(f, params, origin=o) for f, o in zip(seq.frames, seq.origins, strict=True)]


def incremental_icp(
    seq: Sequence,
    init_poses: np.ndarray,
    params: RegistrationParams,
    *,
    on_frame: Callable[[int, np.ndarray], None] | None = None,
    clouds: list[Any] | None = None,
) -> IncrementalResult:
    """Frame-to-frame (or frame-to-local-map) point-to-plane ICP along a sequence.

    Frame k is registered to frame k-1 (to the union of the ``params.local_map`` previous
    frames, placed by their current estimates, when it is above 1), starting from the initial
    guess's relative motion ``init_poses[k-1]^-1 init_poses[k]``; ``poses[0] = init_poses[0]``.

    Args:
        seq: K frames of dimension D.
        init_poses: ``(K, D+1, D+1)`` initial guess (identity or odometry), local -> world.
        params: resolved settings.
        on_frame: called as ``on_frame(k, poses)`` after frame k is placed (``poses`` is the
            ``(K, D+1, D+1)`` working array; frames after k are not yet set); may raise, e.g.
            `strep_core.errors.Cancelled`, to stop.
        clouds: prepared clouds to reuse (`prepare_frames`); made here when ``None``.

    Returns:
        `IncrementalResult` with ``(K, D+1, D+1)`` poses (exactly SE(2) in 2D).
    """
    k_frames = len(seq)
    init_poses = np.asarray(init_poses, dtype=np.float64)
    if init_poses.shape != (k_frames, seq.dim + 1, seq.dim + 1):
        raise RegistrationError(f"init poses have shape {init_poses.shape} for {k_frames} frames of {seq.dim}D")
    started = time.perf_counter()
    with open3d_quiet(params.threads):
        if clouds is None:
            clouds = prepare_frames(seq, params)
        init3 = g.to_se3(init_poses)
        poses3 = np.empty((k_frames, 4, 4))
        poses3[0] = project_planar(init3[0]) if params.planar else init3[0]
        pairs: list[PairResult] = []
        bound = StepBound(STEP_FLOOR * seq.scale())
        fine = params.max_correspondence * min(params.scales)
        for k in range(1, k_frames):
            guess = g.relative(init3[k - 1], init3[k])
            if params.velocity_prior and pairs:
                guess = pairs[-1].transformation
            target = clouds[k - 1]
            if params.local_map > 1:
                target = _local_map(clouds, poses3, k, params)
            prior = step_prior(pairs, stop=params.prior_stop)
            res = icp_pair(clouds[k], target, guess, params, prior=prior)
            res = judge(res, clouds[k], target, guess, params, bound.limit(), fine)
            if res.verdict != "failed":
                bound.add(res)
            pairs.append(res)
            poses3[k] = poses3[k - 1] @ res.transformation
            if params.planar:
                poses3[k] = project_planar(poses3[k])
            if on_frame is not None:
                on_frame(k, from_se3(poses3, seq.dim))
    poses = from_se3(poses3, seq.dim)
    return IncrementalResult(poses=poses, pairs=pairs, clouds=clouds, seconds=time.perf_counter() - started)


STEP_FLOOR = 0.75
"""A chain's step bound never falls below this share of the scale (the planar-laser front
end's floor, half its initial window of 1.5 scales: `strep_core.registration.submaps`)."""


class StepBound:
    """The longest plausible step between two frames, from the chain's own accepted steps.

    Twice the 90th percentile of the last 500 accepted steps once ten are known, never below
    ``floor``; before that, twice the floor. A longer step is unphysical: issue 29's runaway
    chains stepped 22 m where the robot moved 1 m. Turns are not bounded: a hand-held sensor may
    turn as far as it likes between two frames. docs/design/lidar.md, verdicts.
    """

    def __init__(self, floor: float) -> None:
        self.floor = floor
        self.steps: list[float] = []

    def add(self, pair: PairResult) -> None:
        self.steps = [*self.steps[-499:], float(np.linalg.norm(pair.transformation[:3, 3]))]

    def limit(self) -> float:
        if len(self.steps) < 10:
            return 2.0 * self.floor
        return max(2.0 * float(np.percentile(self.steps, 90)), self.floor)


def judge(
    res: PairResult,
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    guess: np.ndarray,
    params: RegistrationParams,
    limit: float,
    distance: float,
) -> PairResult:
    """``res`` with its verdict and covariance (`PairResult`).

    *failed*: ICP kept its guess, or its step is longer than ``limit`` and so is ICP's from the
    guess alone (no yaw search, no global start); then the pair is bridged at ``guess`` with a
    wide covariance (``limit`` in translation, pi in rotation). A step past the bound whose
    guess's own basin lies within it takes that basin: *ambiguous* (two peaks, the far one
    unphysical). Otherwise the covariance is that of the point-to-plane objective at the result
    (`plane_covariance`), so a corridor is uncertain along its axis; *ambiguous* when a
    translation direction kept the guess (``degeneracy``) or carries under 0.02 of the
    strongest's information (the planar-laser front end's ``weak_ratio``), else *accepted*.
    """
    n_t = 2 if params.planar else 3
    wide = np.diag([limit**2] * n_t + [np.pi**2] * (1 if params.planar else 3))
    if res.kept_guess:
        return replace(res, verdict="failed", covariance=wide)
    far = float(np.linalg.norm(res.transformation[:3, 3])) > limit
    if far:
        res = icp_pair(source, target, guess, params, yaw_search=False)
        if res.kept_guess or float(np.linalg.norm(res.transformation[:3, 3])) > limit:
            bridge = project_planar(guess) if params.planar else np.asarray(guess, dtype=np.float64)
            return replace(res, transformation=bridge, verdict="failed", covariance=wide)
    cov = plane_covariance(source, target, res.transformation, distance, planar=params.planar)
    eig = np.linalg.eigvalsh(np.linalg.pinv(cov[:n_t, :n_t]))
    weak = far or res.weak_directions > 0 or eig[0] < 0.02 * max(eig[-1], 1e-12)
    return replace(res, verdict="ambiguous" if weak else "accepted", covariance=cov)


def plane_covariance(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    transform: np.ndarray,
    distance: float,
    *,
    planar: bool = False,
) -> np.ndarray:
    """Covariance of a point-to-plane alignment over (translation, rotation): ``sigma^2 H^-1``.

    ``H = sum J^T J`` with ``J = (n, p x n)`` per source point ``p`` (moved by ``transform``)
    matched within ``distance`` to a target point of normal ``n``, ``sigma^2`` their mean
    squared point-to-plane residual (floored at 1 % of ``distance``, squared). Open3D's own
    information is point-to-point and cannot see a corridor. In 2D: (x, y, theta).
    """
    corr = correspondences(source, target, transform, distance)
    p = np.asarray(source.points)[corr[:, 0]] @ transform[:3, :3].T + transform[:3, 3]
    q, n = np.asarray(target.points)[corr[:, 1]], np.asarray(target.normals)[corr[:, 1]]
    jac = np.hstack([n, np.cross(p - transform[:3, 3], n)])  # rotation about the source's origin
    if planar:
        jac = jac[:, [0, 1, 5]]
    r = np.einsum("ij,ij->i", p - q, n)
    sigma2 = max(float(np.mean(r**2)) if len(r) else 0.0, (0.01 * distance) ** 2)
    h = jac.T @ jac
    h += 1e-9 * max(float(np.trace(h)), 1e-12) * np.eye(len(h))
    return sigma2 * np.linalg.inv(h)


def step_prior(pairs: list[PairResult], n: int = 5, *, stop: float = 0.0) -> np.ndarray | None:
    """The expected next step: the median translation of the last ``n`` pairs (each in its own
    frame), no turn; ``None`` before the first pair. Keyframes are taken at steady spacing, and a
    median forgets one wrong step.

    When that median is a stop (shorter than ``stop``: most recent keyframes were turns in place),
    the median of the last ``n`` longer steps is taken instead, going back as far as needed: after
    a stop to turn, the sensor moves on at its usual step, and a prior of no motion pulls the
    matcher back along a corridor (docs/design/scan-matching.md, fourth part)."""
    if not pairs:
        return None

    def median(chosen: list[PairResult]) -> np.ndarray:
        return np.median(np.stack([p.transformation[:3, 3] for p in chosen]), axis=0)

    t = median(pairs[-n:])
    if stop > 0 and np.linalg.norm(t) < stop:
        moving = []  # the last n longer steps, newest first: a scan back, not over the whole log
        for p in reversed(pairs):
            if np.linalg.norm(p.transformation[:3, 3]) >= stop:
                moving.append(p)
                if len(moving) == n:
                    break
        if moving:
            t = median(moving)
    out = np.eye(4)
    out[:3, 3] = t
    return out


def pair_report(pairs: list[PairResult]) -> tuple[dict[str, Any], dict[str, int]]:
    """A run's report of its ICP pairs (frame k: pair k-1 -> k).

    For its artifacts: the frames where ICP kept its guess (every stage failed) and where weakly
    constrained translation directions were reset to the guess, and ``matches`` (written to
    ``matches.json``): each pair's verdict, fitness, RMSE, step and covariance (`judge`). For
    its metrics: ``icp_kept_guess``, ``icp_weak_pairs``, ``matches_failed`` and
    ``matches_ambiguous``."""
    frames: dict[str, Any] = {
        "kept_guess_frames": [k + 1 for k, p in enumerate(pairs) if p.kept_guess],
        "weak_direction_frames": [k + 1 for k, p in enumerate(pairs) if p.weak_directions],
    }
    kept, weak = frames["kept_guess_frames"], frames["weak_direction_frames"]
    verdicts = [p.verdict for p in pairs]
    counts = {
        "icp_kept_guess": len(kept),
        "icp_weak_pairs": len(weak),
        "matches_failed": verdicts.count("failed"),
        "matches_ambiguous": verdicts.count("ambiguous"),
    }
    frames["matches"] = {
        "pairs": [
            {
                "frame": k + 1,
                "verdict": p.verdict,
                "fitness": round(float(p.fitness), 4),
                "rmse": float(p.inlier_rmse),
                "step": float(np.linalg.norm(p.transformation[:3, 3])),
                "covariance": None if p.covariance is None else np.round(p.covariance, 10).tolist(),
            }
            for k, p in enumerate(pairs)
        ]
    }
    return frames, counts


def _local_map(clouds: list[Any], poses3: np.ndarray, k: int, params: RegistrationParams) -> o3d.geometry.PointCloud:
    """Union of frames ``k-M .. k-1`` in frame k-1's coordinates (normals moved along)."""
    from strep_core._open3d import o3d

    ref = g.inverse(poses3[k - 1])
    merged = o3d.geometry.PointCloud()
    for j in range(max(0, k - params.local_map), k):
        merged += transform_cloud(clouds[j], ref @ poses3[j])
    if params.voxel is not None and not params.planar:
        merged = merged.voxel_down_sample(params.voxel)
    return merged
