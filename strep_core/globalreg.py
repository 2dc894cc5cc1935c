"""Global initial alignment for frames far apart: FPFH features + RANSAC, refined by ICP.

Local methods (ICP, KISS, the learned ones) converge only from a guess within a few tens of
degrees; the views of a multi-view scan (the Stanford bunny: up to 180 degrees apart) need a
global step first. This module offers it as the initial guess ``init="fpfh"``
(`strep_core.runner.initial_guess`).

Conventions as in `strep_core.registration`: poses are ``(D+1, D+1)`` local -> world; a
pairwise result ``T`` maps source into target coordinates. 2D frames run in 3D at ``z = 0``
and every estimate is projected onto SE(2) (FPFH is a 3D descriptor: 2D is accepted, not tuned).

Per frame k (``fpfh_poses``):

1. features: each frame is voxel-downsampled at ``v`` (the *feature voxel*), given normals
   (radius ``2 v``, facing the frame's sensor origin) and FPFH descriptors (radius ``5 v``);
2. the target is the union of the frames already placed (``target="union"``, the default), or
   frame k-1 alone (``"previous"``), in frame 0's world coordinates, downsampled again at ``v``
   (normals are carried along, so they keep facing their own sensors);
3. RANSAC over mutual nearest FPFH matches (3 per hypothesis, edge-length and distance
   checkers, distance ``1.5 v``), seeded: Open3D's global generator is reseeded with
   ``seed + k`` before each call and the work runs on ``threads`` threads (1: repeatable);
4. two candidates are refined by coarse-to-fine point-to-plane ICP against the same target
   (on finer clouds: `strep_core.registration.prepare_frame` at voxel ``v / 2``, normal
   radius ``v``): the RANSAC estimate
   and the base guess's motion (``P_{k-1} B_{k-1}^-1 B_k``); the one matching more source
   points (ICP fitness at the finest distance; then the lower RMSE) places frame k. Where
   the base guess is already right (consecutive depth frames) FPFH cannot make things worse.

Data-derived lengths, with ``s = Sequence.scale()``: feature voxel ``v = 0.03 s`` (3.9 mm on
the bunny, s = 0.129 m; 6 cm on 7-Scenes, s = 2 m); ICP refinement distances ``(4, 2, 1) v``.

Measured on the Stanford bunny (10 scans, 2 mm voxel, 1 thread; see ``docs/real3d.md``):
against the union every view lands within 2.4 degrees and 3.1 mm of the reference (9 s);
against the previous view alone the last one (``chin`` -> ``ear_back``, 168 degrees apart,
little overlap) is lost.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from strep_core import geometry as g
from strep_core import registration as reg
from strep_core.errors import RegistrationError
from strep_core.sequence import Sequence

if TYPE_CHECKING:  # pragma: no cover
    from strep_core._open3d import o3d

__all__ = [
    "GlobalParams",
    "GlobalResult",
    "fpfh_features",
    "fpfh_poses",
    "global_pair",
    "ransac_pair",
    "resolve_global_params",
]

GlobalTarget = Literal["union", "previous"]


@dataclass(frozen=True)
class GlobalParams:
    """Absolute settings of the global alignment; build them with `resolve_global_params`.

    Attributes:
        voxel: feature voxel ``v`` (sequence unit): downsampling before FPFH.
        normal_radius: normal estimation radius (sequence unit), default ``2 v``.
        feature_radius: FPFH radius (sequence unit), default ``5 v``.
        normal_max_nn, feature_max_nn: neighbour caps of those searches.
        ransac_distance: inlier distance of RANSAC (sequence unit), default ``1.5 v``.
        ransac_iterations: RANSAC hypotheses at most.
        ransac_confidence: RANSAC stops early at this confidence.
        edge_length: edge-length checker similarity (0.9: edges agree within 10 %).
        mutual: keep only mutual nearest feature matches.
        refine_distance: finest ICP distance of the refinement (sequence unit), default ``v``.
        refine_scales: coarse-to-fine multipliers of ``refine_distance``.
        target: ``"union"`` of the frames already placed, or the ``"previous"`` frame.
        map_frames: with ``"union"``: at most this many latest placed frames (``None``: all).
        seed: RANSAC seed; frame k uses ``seed + k``.
        threads: Open3D threads (1 makes RANSAC repeatable).
    """

    voxel: float
    normal_radius: float
    feature_radius: float
    ransac_distance: float
    refine_distance: float
    normal_max_nn: int = 30
    feature_max_nn: int = 100
    ransac_iterations: int = 100_000
    ransac_confidence: float = 0.999
    edge_length: float = 0.9
    mutual: bool = True
    refine_scales: tuple[float, ...] = (4.0, 2.0, 1.0)
    target: GlobalTarget = "union"
    map_frames: int | None = None
    seed: int = 0
    threads: int = 1


def resolve_global_params(
    seq: Sequence,
    *,
    voxel: float | None = None,
    voxel_fraction: float = 0.03,
    target: GlobalTarget = "union",
    map_frames: int | None = None,
    seed: int = 0,
    threads: int = 1,
    ransac_iterations: int = 100_000,
) -> GlobalParams:
    """Settings for ``seq``: feature voxel ``v = voxel`` or ``voxel_fraction * scale`` and the
    lengths derived from it (normals ``2 v``, FPFH ``5 v``, RANSAC ``1.5 v``, ICP ``(4, 2, 1) v``).
    """
    v = float(voxel) if voxel is not None else voxel_fraction * seq.scale()
    if not v > 0:
        raise RegistrationError(f"the FPFH voxel must be positive, not {v}")
    if target not in ("union", "previous"):
        raise RegistrationError(f"FPFH target is 'union' or 'previous', not {target!r}")
    return GlobalParams(
        voxel=v,
        normal_radius=2.0 * v,
        feature_radius=5.0 * v,
        ransac_distance=1.5 * v,
        refine_distance=v,
        ransac_iterations=int(ransac_iterations),
        target=target,
        map_frames=map_frames,
        seed=int(seed),
        threads=int(threads),
    )


@dataclass
class GlobalResult:
    """Output of `fpfh_poses`.

    Attributes:
        poses: ``(K, D+1, D+1)`` local -> world, ``poses[0]`` = the base guess's.
        choices: per frame k >= 1, the candidate that placed it: ``"fpfh"`` or ``"base"``.
        fitness: per frame k >= 1, the ICP fitness of the chosen candidate.
        ransac_fitness: per frame k >= 1, RANSAC's own inlier fraction.
        seconds: wall time.
    """

    poses: np.ndarray
    choices: list[str] = field(default_factory=list)
    fitness: list[float] = field(default_factory=list)
    ransac_fitness: list[float] = field(default_factory=list)
    seconds: float = 0.0


# --------------------------------------------------------------------------------------------
# Features and pairwise RANSAC


def _feature_cloud(points: np.ndarray, params: GlobalParams, origin: np.ndarray | None) -> o3d.geometry.PointCloud:
    """Downsampled cloud (3D, ``z = 0`` for 2D) with unit normals facing ``origin``."""
    from strep_core._open3d import o3d

    points = np.asarray(points, dtype=np.float64)
    dim = points.shape[1]
    cloud = reg.make_cloud(points).voxel_down_sample(params.voxel)
    if len(cloud.points) < 3:
        raise RegistrationError(f"a frame keeps {len(cloud.points)} points at the FPFH voxel {params.voxel:.3g}")
    origin = np.zeros(dim) if origin is None else np.asarray(origin, dtype=np.float64)
    if dim == 2:
        normals = reg.normals_2d(np.asarray(cloud.points)[:, :2], origin=origin)
        cloud.normals = o3d.utility.Vector3dVector(g.pad_points(normals))
    else:
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=params.normal_radius, max_nn=params.normal_max_nn)
        )
        cloud.orient_normals_towards_camera_location(origin)
    return cloud


def _fpfh(cloud: o3d.geometry.PointCloud, params: GlobalParams) -> Any:
    from strep_core._open3d import o3d

    search = o3d.geometry.KDTreeSearchParamHybrid(radius=params.feature_radius, max_nn=params.feature_max_nn)
    # Open3D 0.20's stub marks the optional ``indices`` (a subset of points) as required
    return o3d.pipelines.registration.compute_fpfh_feature(cloud, search)  # type: ignore[call-arg]


def fpfh_features(
    points: np.ndarray, params: GlobalParams, *, origin: np.ndarray | None = None
) -> tuple[o3d.geometry.PointCloud, Any]:
    """FPFH descriptors of one frame.

    Args:
        points: ``(N, D)`` points in the frame's coordinates.
        params: settings (voxel, radii).
        origin: ``(D,)`` sensor position; normals face it (``None``: the origin).

    Returns:
        The downsampled Open3D cloud (with normals) and its ``(33, M)`` Open3D ``Feature``.
    """
    from strep_core._open3d import o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = _feature_cloud(points, params, origin)
        return cloud, _fpfh(cloud, params)


def _ransac(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    source_feature: Any,
    target_feature: Any,
    params: GlobalParams,
    seed: int,
) -> reg.PairResult:
    from strep_core._open3d import o3d

    r = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    res = r.registration_ransac_based_on_feature_matching(
        source,
        target,
        source_feature,
        target_feature,
        params.mutual,
        params.ransac_distance,
        r.TransformationEstimationPointToPoint(False),
        3,
        [
            r.CorrespondenceCheckerBasedOnEdgeLength(params.edge_length),
            r.CorrespondenceCheckerBasedOnDistance(params.ransac_distance),
        ],
        r.RANSACConvergenceCriteria(params.ransac_iterations, params.ransac_confidence),
    )
    return reg.PairResult(np.asarray(res.transformation).copy(), float(res.fitness), float(res.inlier_rmse))


def ransac_pair(
    source: np.ndarray,
    target: np.ndarray,
    params: GlobalParams,
    *,
    source_origin: np.ndarray | None = None,
    target_origin: np.ndarray | None = None,
) -> reg.PairResult:
    """Global source -> target alignment of two frames by FPFH + RANSAC, without refinement.

    Args:
        source, target: ``(N, D)`` and ``(M, D)`` points, each in its local coordinates.
        params: settings; ``params.seed`` seeds RANSAC.
        source_origin, target_origin: ``(D,)`` sensor positions (normals face them).

    Returns:
        `PairResult` with a ``(4, 4)`` transform (not projected in 2D) and RANSAC's inlier
        fraction and RMSE at ``ransac_distance``.
    """
    with reg.open3d_quiet(params.threads):
        src, fs = fpfh_features(source, params, origin=source_origin)
        tgt, ft = fpfh_features(target, params, origin=target_origin)
        return _ransac(src, tgt, fs, ft, params, params.seed)


def _refine(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: np.ndarray, gp: GlobalParams, planar: bool
) -> reg.PairResult:
    params = reg.RegistrationParams(
        dim=2 if planar else 3, max_correspondence=gp.refine_distance, scales=tuple(gp.refine_scales), iterations=50
    )
    return reg.icp_pair(source, target, reg.project_planar(init) if planar else init, params)


def _score(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, transform: np.ndarray, gp: GlobalParams
) -> reg.PairResult:
    """Fitness and RMSE of ``transform`` at the finest refinement distance (same yardstick for all)."""
    from strep_core._open3d import o3d

    ev = o3d.pipelines.registration.evaluate_registration(source, target, gp.refine_distance, transform)
    return reg.PairResult(np.asarray(transform, dtype=np.float64), float(ev.fitness), float(ev.inlier_rmse))


def global_pair(
    source: np.ndarray,
    target: np.ndarray,
    params: GlobalParams,
    *,
    registration: reg.RegistrationParams | None = None,
    source_origin: np.ndarray | None = None,
    target_origin: np.ndarray | None = None,
) -> tuple[np.ndarray, reg.PairResult]:
    """FPFH + RANSAC, then coarse-to-fine point-to-plane ICP, for two frames.

    Args:
        source, target: ``(N, D)`` and ``(M, D)`` points, each in its local coordinates.
        params: global settings.
        registration: settings of the refinement's ICP clouds (voxel, normals); ``None``:
            voxel ``v / 2``, normal radius ``v``.
        source_origin, target_origin: ``(D,)`` sensor positions.

    Returns:
        ``(D+1, D+1)`` source -> target transform and the refinement's `PairResult`.
    """
    dim = np.asarray(source).shape[1]
    rp = registration or _fallback_registration(dim, params)
    with reg.open3d_quiet(params.threads):
        coarse = ransac_pair(source, target, params, source_origin=source_origin, target_origin=target_origin)
        src = reg.prepare_frame(source, rp, origin=source_origin)
        tgt = reg.prepare_frame(target, rp, origin=target_origin)
        res = _refine(src, tgt, coarse.transformation, params, dim == 2)
    return reg.from_se3(res.transformation, dim), res


def _fallback_registration(dim: int, params: GlobalParams) -> reg.RegistrationParams:
    return reg.RegistrationParams(
        dim=dim,
        max_correspondence=params.refine_distance,
        voxel=params.voxel / 2,
        normal_radius=params.normal_radius / 2,
        threads=params.threads,
    )


# --------------------------------------------------------------------------------------------
# Sequences


def _merge(clouds: list[Any], poses3: np.ndarray, frames: range, voxel: float | None) -> o3d.geometry.PointCloud:
    """Union of ``clouds[j]`` placed by ``poses3[j]`` (normals carried), downsampled at ``voxel``."""
    from strep_core._open3d import o3d

    merged = o3d.geometry.PointCloud()
    for j in frames:
        merged += reg.transform_cloud(clouds[j], poses3[j])
    if voxel is not None and len(frames) > 1:
        merged = merged.voxel_down_sample(voxel)
        merged.normalize_normals()
    return merged


def fpfh_poses(
    seq: Sequence,
    base_poses: np.ndarray,
    params: GlobalParams,
    *,
    registration: reg.RegistrationParams | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> GlobalResult:
    """Place every frame by FPFH + RANSAC and ICP against the frames placed before it.

    See the module docstring for the steps. ``poses[0] = base_poses[0]``.

    Args:
        seq: K frames of dimension D (with sensor origins).
        base_poses: ``(K, D+1, D+1)`` base guess (identity or odometry), local -> world: it
            anchors frame 0 and gives each frame a second candidate (its relative motion).
        params: global settings (`resolve_global_params`).
        registration: settings of the refinement's ICP clouds (voxel, normals); ``None``:
            voxel ``v / 2``, normal radius ``v``.
        on_frame: called as ``on_frame(k)`` after frame k is placed (may raise to cancel).

    Returns:
        `GlobalResult` with ``(K, D+1, D+1)`` poses (exactly SE(2) in 2D).

    Raises:
        RegistrationError: wrong pose shape, or a frame too small for the feature voxel.
    """
    k_frames, dim = len(seq), seq.dim
    base_poses = np.asarray(base_poses, dtype=np.float64)
    if base_poses.shape != (k_frames, dim + 1, dim + 1):
        raise RegistrationError(f"base poses have shape {base_poses.shape} for {k_frames} frames of {dim}D")
    rp = registration or _fallback_registration(dim, params)
    planar = dim == 2
    assert seq.origins is not None
    started = time.perf_counter()
    base3 = g.to_se3(base_poses)
    poses3 = np.empty((k_frames, 4, 4))
    poses3[0] = reg.project_planar(base3[0]) if planar else base3[0]
    out = GlobalResult(poses=np.empty(0))
    with reg.open3d_quiet(params.threads):
        feats = [_feature_cloud(f, params, o) for f, o in zip(seq.frames, seq.origins, strict=True)]
        fine = reg.prepare_frames(seq, rp)
        for k in range(1, k_frames):
            if params.target == "previous":
                span = range(k - 1, k)
            else:
                span = range(0 if params.map_frames is None else max(0, k - params.map_frames), k)
            feat_map = _merge(feats, poses3, span, params.voxel)
            fine_map = _merge(fine, poses3, span, rp.voxel)
            ransac = _ransac(
                feats[k], feat_map, _fpfh(feats[k], params), _fpfh(feat_map, params), params, params.seed + k
            )
            guesses = {"fpfh": ransac.transformation, "base": poses3[k - 1] @ g.relative(base3[k - 1], base3[k])}
            candidates = {}
            for name, guess in guesses.items():
                refined = _refine(fine[k], fine_map, guess, params, planar)
                candidates[name] = _score(fine[k], fine_map, refined.transformation, params)
            choice = max(candidates, key=lambda c: (candidates[c].fitness, -candidates[c].inlier_rmse))
            best = candidates[choice]
            poses3[k] = reg.project_planar(best.transformation) if planar else best.transformation
            out.choices.append(choice)
            out.fitness.append(best.fitness)
            out.ransac_fitness.append(ransac.fitness)
            if on_frame is not None:
                on_frame(k)
    out.poses = reg.from_se3(poses3, dim)
    out.seconds = time.perf_counter() - started
    return out
