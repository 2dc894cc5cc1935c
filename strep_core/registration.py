"""Pairwise and incremental rigid registration with Open3D, shared by the classical baselines
and by the learned methods' warm starts.

Conventions (see `strep_core.geometry`): poses are homogeneous ``(D+1, D+1)`` matrices,
local -> world; lengths are in the sequence's unit (pixels or metres).

* A pairwise result ``T`` maps *source* coordinates into *target* coordinates:
  ``p_target = T p_source``. With world poses ``P_s, P_t``: ``T = P_t^-1 P_s``
  (``geometry.relative(P_t, P_s)``).
* 2D frames are registered in 3D as ``z = 0`` points with in-plane normals (`normals_2d`);
  every 3D estimate is projected back onto SE(2) (`project_planar`), so 2D results are
  exactly SE(2).
* Open3D's *legacy* pipeline (`o3d.pipelines.registration`) is used: its tensor API is about
  30x slower on CPU. Open3D is imported inside functions (it is heavy).

Data-derived lengths (`resolve_params`), with ``s = Sequence.scale()`` (median point range):

* correspondence distance ``d = correspondence_fraction * s`` (default 0.16 s: 20 px on
  DeepMapping's v1_pose0, where s = 125 px; 10 px diverges there); ICP runs coarse to fine
  over ``icp_scales * d``;
* voxel ``v = voxel_fraction * s`` (default 0.01 s: 1.2 px, 2 cm on a 2 m CARMEN scan,
  1.5 to 2 cm on indoor RGB-D);
* 3D normal radius ``normal_radius_factor * max(v, h)``, ``h`` the median spacing of
  neighbouring points (`point_spacing`), so that sparse clouds still find neighbours;
  2D normals from the ``normal_neighbours`` nearest neighbours in the plane.

Global scan match (on by default for 2D data, ``icp_global``): each pair also runs ICP from the
best pose of `strep_core.scanmatch` (every heading, +-1.5 s, with a prior on the median of the last
steps); when that ICP result lands in another basin than ICP from the guess, the higher matcher
score wins.

Optional guards (off by default; the profile a run picks from its data turns them on,
`strep_core.profiles`):

* yaw search (``icp_yaw_search``, ``icp_yaw_step``): the coarsest stage also starts from the
  guess turned about the sensor's vertical axis (``z`` in 2D, ``icp_yaw_axis`` in 3D), and the
  best-matching start goes on;
* weak directions (``icp_degeneracy``): after the last stage, translation along directions the
  matched normals barely constrain returns to the guess's (`keep_guess_where_weak`).

Each `PairResult` says whether ICP failed and kept its guess and how many directions were
reset; `pair_report` lists those frames and counts them for a run's artifacts and metrics.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from strep_core import geometry as g
from strep_core.config import ClassicalConfig
from strep_core.correlative import CorrelativeParams, correlative_match
from strep_core.errors import RegistrationError
from strep_core.scanmatch import ScanMatcher, ScanMatchParams
from strep_core.sequence import Sequence

if TYPE_CHECKING:  # pragma: no cover
    from strep_core._open3d import o3d


@dataclass(frozen=True)
class RegistrationParams:
    """Absolute registration settings for one sequence; build them with `resolve_params`.

    Attributes:
        dim: spatial dimension D of the frames (2 or 3).
        max_correspondence: finest ICP correspondence distance (sequence unit).
        scales: coarse-to-fine multipliers of ``max_correspondence``, one ICP stage each.
        iterations: ICP iterations per stage.
        min_fitness: ICP stages matching fewer source points than this fraction are discarded.
        kernel: Tukey kernel width as a fraction of each stage's distance; ``None``: plain L2.
        voxel: voxel size for downsampling (sequence unit); ``None``: keep every point.
        normal_neighbours: 2D normals: neighbours of the in-plane PCA (the point included).
        normal_radius: 3D normals: search radius (sequence unit).
        normal_max_nn: 3D normals: at most this many neighbours within the radius.
        local_map: incremental ICP registers frame k to the union of this many previous frames.
        threads: CPU threads Open3D may use (1 makes runs bit-for-bit repeatable).
        yaw_search: extra yaw offsets (radians) tried as starting guesses of the coarsest ICP
            stage (see `register_clouds`); empty: the initial guess alone.
        yaw_axis: unit axis of those turns in the source sensor's frame (``z`` in 2D).
        degeneracy: keep the guess's translation along weakly constrained directions (see
            `register_clouds`); 0: off.
        correlative: 2D: also start from a correlative scan match (see `register_clouds`).
        velocity_prior: incremental ICP starts each pair from the previous pair's estimated
            motion (constant velocity) instead of the initial guess's relative motion.
        global_match: 2D: also start from a global scan match (see `register_with`).
        prior_stop: a global match's step prior shorter than this (sequence unit) is a stop:
            the median of the last longer steps replaces it (`_step_prior`); 0: never.
    """

    dim: int
    max_correspondence: float
    scales: tuple[float, ...] = (1.0,)
    iterations: int = 50
    min_fitness: float = 0.0
    kernel: float | None = None
    voxel: float | None = None
    normal_neighbours: int = 6
    normal_radius: float = 1.0
    normal_max_nn: int = 30
    local_map: int = 1
    threads: int = 1
    yaw_search: tuple[float, ...] = ()
    yaw_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    degeneracy: float = 0.0
    correlative: CorrelativeParams | None = None
    velocity_prior: bool = False
    global_match: ScanMatchParams | None = None
    prior_stop: float = 0.0

    @property
    def planar(self) -> bool:
        return self.dim == 2


def resolve_params(seq: Sequence, cfg: ClassicalConfig) -> RegistrationParams:
    """Turn a `ClassicalConfig` into absolute lengths for ``seq`` (rules in the module doc)."""
    s = seq.scale()
    voxel = cfg.voxel if cfg.voxel is not None else cfg.voxel_fraction * s
    normal_radius = cfg.normal_radius if cfg.normal_radius is not None else 1.0
    if cfg.normal_radius is None and seq.dim == 3:  # 2D normals use neighbour counts, not a radius
        normal_radius = cfg.normal_radius_factor * max(voxel, point_spacing(seq))
    axis: tuple[float, float, float] | None = None
    if cfg.icp_yaw_axis is not None:
        a = np.asarray(cfg.icp_yaw_axis, dtype=np.float64)
        x, y, z = (float(c) for c in a / np.linalg.norm(a))
        axis = (x, y, z)
    d = cfg.max_correspondence if cfg.max_correspondence is not None else cfg.correspondence_fraction * s
    correlative = None
    if cfg.icp_correlative > 0 and seq.dim == 2:
        correlative = CorrelativeParams(
            window=cfg.icp_correlative * d,
            yaw_window=float(np.radians(cfg.icp_correlative_yaw)),
            yaw_step=float(np.radians(1.0)),
            resolution=d / 7.0,
            sigma=d / 3.5,
        )
    global_match = None
    if seq.dim == 2 and cfg.icp_global != "off":
        global_match = ScanMatchParams(
            window=cfg.icp_global_window * s,
            resolution=cfg.icp_global_resolution * s,
            yaw_step=float(np.radians(cfg.icp_global_yaw_step)),
            yaw_window=float(np.radians(cfg.icp_global_yaw_window)),
            max_range=cfg.icp_global_range * s,
            prior_weight=cfg.icp_global_prior,
            prior_scale=s,
        )
    return RegistrationParams(
        dim=seq.dim,
        max_correspondence=d,
        scales=tuple(cfg.icp_scales),
        iterations=cfg.icp_iterations,
        min_fitness=cfg.icp_min_fitness,
        kernel=cfg.icp_kernel,
        voxel=voxel if voxel > 0 else None,
        normal_neighbours=cfg.normal_neighbours,
        normal_radius=normal_radius,
        normal_max_nn=cfg.normal_max_nn,
        local_map=cfg.local_map_frames,
        threads=cfg.threads,
        yaw_search=yaw_offsets(cfg.icp_yaw_search, cfg.icp_yaw_step) if seq.dim == 2 or axis is not None else (),
        yaw_axis=(0.0, 0.0, 1.0) if axis is None or seq.dim == 2 else axis,
        degeneracy=cfg.icp_degeneracy,
        correlative=correlative,
        velocity_prior=cfg.icp_motion_prior == "velocity",
        global_match=global_match,
        prior_stop=cfg.icp_global_prior_stop * s,
    )


def yaw_offsets(half_width_deg: float, step_deg: float) -> tuple[float, ...]:
    """Nonzero yaw offsets ``+-step, +-2 step, ...`` up to ``half_width`` (degrees in, radians out),
    nearest first."""
    if half_width_deg <= 0 or step_deg <= 0:
        return ()
    n = int(np.floor(half_width_deg / step_deg + 1e-9))
    return tuple(float(np.radians(sign * i * step_deg)) for i in range(1, n + 1) for sign in (1, -1))


@dataclass(frozen=True)
class PairResult:
    """One pairwise registration.

    Attributes:
        transformation: ``(4, 4)`` source -> target in the 3D embedding (``z = 0`` in 2D,
            then exactly SE(2) embedded: yaw and x, y only).
        fitness: fraction of source points with a correspondence within the final distance.
        inlier_rmse: RMSE of those correspondences (sequence unit).
        kept_guess: every ICP stage failed (see ``min_fitness``): the transform is the guess.
        weak_directions: how many translation directions were too weakly constrained by the
            matched normals and kept the guess's value (``degeneracy``).
    """

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    kept_guess: bool = False
    weak_directions: int = 0


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


# --------------------------------------------------------------------------------------------
# Small helpers


def point_spacing(seq: Sequence, *, max_frames: int = 4) -> float:
    """Median distance from a point to its nearest neighbour in the same frame (sequence unit).

    Measured on up to ``max_frames`` evenly spaced frames; the density of the data, where
    `Sequence.scale` is its extent (sparse 2D scan lines: about 0.02 of the scale; dense
    depth images subsampled 4x: about 0.007).
    """
    from scipy.spatial import cKDTree

    step = max(1, len(seq) // max(1, max_frames))
    d = np.concatenate([cKDTree(f).query(f, k=2)[0][:, 1] for f in seq.frames[::step][:max_frames]])
    d = d[d > 0]
    return float(np.median(d)) if len(d) else seq.scale() * 1e-3


@contextlib.contextmanager
def open3d_quiet(threads: int | None = None) -> Iterator[Any]:
    """Import Open3D, silence its log and bound its threads (then restore them); yields the module."""
    from strep_core._open3d import o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        if threads is None:
            yield o3d
            return
        previous = o3d.utility.get_max_threads()
        o3d.utility.set_max_threads(int(threads))
        try:
            yield o3d
        finally:
            o3d.utility.set_max_threads(previous)


def project_planar(transform: np.ndarray) -> np.ndarray:
    """Nearest planar motion of 3D transforms ``(..., 4, 4)``: keep yaw and x, y; z = 0.

    Returns ``(..., 4, 4)`` SE(2) poses embedded in SE(3) (rotation about z only).
    """
    transform = np.asarray(transform, dtype=np.float64)
    yaw = np.arctan2(transform[..., 1, 0] - transform[..., 0, 1], transform[..., 0, 0] + transform[..., 1, 1])
    out = np.zeros_like(transform)
    c, s = np.cos(yaw), np.sin(yaw)
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 0, 3], out[..., 1, 3] = transform[..., 0, 3], transform[..., 1, 3]
    out[..., 2, 2] = out[..., 3, 3] = 1.0
    return out


def from_se3(transform: np.ndarray, dim: int) -> np.ndarray:
    """``(..., 4, 4)`` -> poses of dimension ``dim``: ``(..., 3, 3)`` SE(2) (projected) or as is."""
    if dim == 3:
        return np.asarray(transform, dtype=np.float64)
    planar = project_planar(transform)
    out = np.zeros((*planar.shape[:-2], 3, 3))
    out[..., :2, :2] = planar[..., :2, :2]
    out[..., :2, 2] = planar[..., :2, 3]
    out[..., 2, 2] = 1.0
    return out


def normals_2d(points: np.ndarray, *, neighbours: int = 6, origin: np.ndarray | None = None) -> np.ndarray:
    """Unit normals of 2D points from a PCA of each point's nearest neighbours.

    The normal is the eigenvector of the smallest eigenvalue of the neighbourhood covariance.

    Args:
        points: ``(N, 2)`` points.
        neighbours: neighbourhood size, the point itself included (at least 2; capped at N).
        origin: ``(2,)`` sensor position; normals are flipped to face it (``None``: the origin).

    Returns:
        ``(N, 2)`` unit normals.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise RegistrationError(f"normals_2d needs (N, 2) points, got {points.shape}")
    k = min(max(int(neighbours), 2), len(points))
    if k < 2:
        raise RegistrationError("normals_2d needs at least 2 points")
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx]  # (N, k, 2)
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred)
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    normals = vecs[:, :, 0]
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    view = (np.zeros(2) if origin is None else np.asarray(origin, dtype=np.float64)) - points
    flip = np.einsum("ni,ni->n", normals, view) < 0
    normals[flip] *= -1.0
    return normals


def make_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """An Open3D point cloud from ``(N, 2|3)`` points (2D embedded at ``z = 0``) and normals."""
    from strep_core._open3d import o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(g.pad_points(np.asarray(points, np.float64))))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(g.pad_points(np.asarray(normals, np.float64)))
    return cloud


def prepare_frame(
    points: np.ndarray, params: RegistrationParams, *, origin: np.ndarray | None = None
) -> o3d.geometry.PointCloud:
    """Downsample one frame and give it normals, ready for point-to-plane ICP.

    Args:
        points: ``(N, D)`` points in the frame's local coordinates.
        params: resolved settings (voxel, normal neighbourhood).
        origin: ``(D,)`` sensor position in the same coordinates; normals face it.

    Returns:
        An Open3D cloud in 3D (``z = 0`` for 2D frames) with unit normals.
    """
    from strep_core._open3d import o3d

    points = np.asarray(points, dtype=np.float64)
    dim = points.shape[1]
    origin = np.zeros(dim) if origin is None else np.asarray(origin, dtype=np.float64)
    cloud = make_cloud(points)
    if params.voxel is not None:
        cloud = cloud.voxel_down_sample(params.voxel)
    if len(cloud.points) < 3:
        raise RegistrationError(f"a frame keeps {len(cloud.points)} points after downsampling; need 3")
    if dim == 2:
        pts2 = np.asarray(cloud.points)[:, :2]
        cloud.normals = o3d.utility.Vector3dVector(
            g.pad_points(normals_2d(pts2, neighbours=params.normal_neighbours, origin=origin))
        )
    else:
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=params.normal_radius, max_nn=params.normal_max_nn)
        )
        cloud.orient_normals_towards_camera_location(origin)
    return cloud


# --------------------------------------------------------------------------------------------
# Pairwise registration


def register_clouds(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    *,
    max_correspondence: float,
    scales: tuple[float, ...] = (1.0,),
    iterations: int = 50,
    planar: bool = False,
    min_fitness: float = 0.0,
    kernel: float | None = None,
    yaw_search: tuple[float, ...] = (),
    yaw_axis: tuple[float, float, float] = (0.0, 0.0, 1.0),
    degeneracy: float = 0.0,
    correlative: CorrelativeParams | None = None,
) -> PairResult:
    """Point-to-plane ICP of prepared clouds (``target`` needs normals), coarse to fine.

    Args:
        source, target: Open3D clouds (see `prepare_frame`).
        init: ``(4, 4)`` initial source -> target transform.
        max_correspondence: finest correspondence distance (sequence unit).
        scales: one ICP stage per multiplier of ``max_correspondence``, in the given order.
        iterations: maximum ICP iterations per stage.
        planar: project every stage's result onto SE(2) (2D frames at ``z = 0``).
        min_fitness: a stage whose result matches fewer than this fraction of the source
            points (or none) is discarded with the stages after it: the transform stays where
            the previous stage left it (the initial guess if it is the first). This stops the
            rare runaway of point-to-plane ICP on a few degenerate correspondences.
        kernel: Tukey robust-kernel width as a fraction of each stage's distance (``None``: L2).
        yaw_search: yaw offsets (radians, about the source's origin, i.e. its sensor) added to
            ``init`` as extra starting guesses. The coarsest stage runs from each; the result
            that matches the most source points within the *finest* distance (ties: the lower
            RMSE) goes on to the finer stages. Point-to-plane ICP converges only from within
            about 10 degrees; laser keyframes turn by up to 20 to 30 degrees.
        yaw_axis: unit axis of the yaw turns, in the source's frame (its sensor's vertical).
        degeneracy: after the last stage, the translation along each direction whose
            eigenvalue of the mean outer product of the matched target normals (finest
            distance) is below this is reset to the guess's (`keep_guess_where_weak`):
            ICP slides freely along a wall or a corridor, and the guess (the previous motion,
            or no motion) is the better answer there. 0: off.
        correlative: 2D only: the stages also run from the best pose of a correlative scan
            match around ``init`` (`strep_core.correlative`; no yaw search from there), and
            that result wins when it matches more source points within the finest distance
            (by more than 0.01 of them). It finds turns and offsets beyond every ICP basin the
            yaw search can reach.
    """
    params = RegistrationParams(
        dim=2 if planar else 3,
        max_correspondence=max_correspondence,
        scales=tuple(scales),
        iterations=iterations,
        min_fitness=min_fitness,
        kernel=kernel,
        yaw_search=tuple(yaw_search),
        yaw_axis=yaw_axis,
        degeneracy=degeneracy,
        correlative=correlative,
    )
    return register_with(source, target, init, params)


def register_with(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    params: RegistrationParams,
    *,
    scales: tuple[float, ...] | None = None,
    yaw_search: bool = True,
    prior: np.ndarray | None = None,
) -> PairResult:
    """Pairwise ICP with every setting from ``params`` (what each does: `register_clouds`).

    ``scales`` overrides its stages; ``yaw_search=False`` starts from ``init`` alone, without the
    yaw search or the correlative start (e.g. for loop closures)."""
    stages = params.scales if scales is None else tuple(scales)
    first = _register(source, target, init, params, stages, params.yaw_search if yaw_search else ())
    if not params.planar or not yaw_search or (params.correlative is None and params.global_match is None):
        return first
    from strep_core._open3d import o3d

    guess = from_se3(project_planar(init)[None], 2)[0]
    src2, tgt2 = np.asarray(source.points)[:, :2], np.asarray(target.points)[:, :2]
    best = first
    if params.global_match is not None:
        # one objective decides: the matcher's score (likelihood field + motion prior) of each
        # ICP result; ICP from the global match wins only when it scores higher
        t_prior = None if prior is None else np.asarray(prior, dtype=np.float64)[:2, -1]
        matcher = ScanMatcher(tgt2, params.global_match, center=guess[:2, 2])
        found = matcher.match(src2, guess, prior=t_prior)
        other = _register(source, target, g.to_se3(found.pose), params, stages, ())
        poses2 = [from_se3(r.transformation[None], 2)[0] for r in (first, other)]
        apart = g.relative(poses2[0], poses2[1])
        gm = params.global_match
        # the same basin (within two cells and two yaw steps): keep ICP from the guess, which the
        # grid cannot tell apart from it; another basin: the higher score (prior included)
        same = (
            np.linalg.norm(apart[:2, 2]) <= 2 * gm.resolution
            and abs(float(np.arctan2(apart[1, 0], apart[0, 0]))) <= 2 * gm.yaw_step
        )
        if not same and matcher.evaluate(src2, poses2[1], prior=t_prior) > matcher.evaluate(
            src2, poses2[0], prior=t_prior
        ):
            best = other
    if params.correlative is None:
        return best
    fine = params.max_correspondence * min(stages)
    evaluate = o3d.pipelines.registration.evaluate_registration
    start, _ = correlative_match(src2, tgt2, guess, params.correlative)
    second = _register(source, target, g.to_se3(start), params, stages, ())
    fit = [evaluate(source, target, fine, r.transformation).fitness for r in (best, second)]
    return second if fit[1] > fit[0] + 0.01 else best


def _register(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    params: RegistrationParams,
    scales: tuple[float, ...],
    yaw_search: tuple[float, ...],
) -> PairResult:
    """The ICP stages ``scales`` from ``init`` (after the yaw search, when ``yaw_search`` has
    offsets) and the weak-direction guard: `register_with` without the correlative start."""
    from strep_core._open3d import o3d

    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=int(params.iterations)
    )
    if not scales:
        raise RegistrationError("register_clouds needs at least one scale")
    planar, d = params.planar, params.max_correspondence
    current = project_planar(init) if planar else np.asarray(init, dtype=np.float64)
    guess, fitness, rmse = current, 0.0, 0.0
    stages = tuple(scales)
    if yaw_search:
        # the search runs the coarsest stage from every start: go on from its best result
        best = _best_yaw_start(
            source,
            target,
            current,
            yaw_search,
            d * scales[0],
            d * min(scales),
            criteria=criteria,
            planar=planar,
            min_fitness=params.min_fitness,
            kernel=params.kernel,
            axis=params.yaw_axis,
        )
        if best is None:  # the coarsest stage failed from every start, ``init`` included
            return PairResult(transformation=current, fitness=0.0, inlier_rmse=0.0, kept_guess=True)
        (current, fitness, rmse), stages = best, stages[1:]
    moved = bool(yaw_search)
    for scale in stages:
        stage = _icp_stage(
            source,
            target,
            current,
            d * scale,
            kernel=params.kernel,
            criteria=criteria,
            planar=planar,
            min_fitness=params.min_fitness,
        )
        if stage is None:
            break
        current, fitness, rmse = stage
        moved = True
    if not moved:
        return PairResult(transformation=current, fitness=0.0, inlier_rmse=0.0, kept_guess=True)
    weak = 0
    if params.degeneracy > 0:
        current, weak = keep_guess_where_weak(
            source, target, current, guess, d * min(scales), params.degeneracy, planar=planar
        )
    return PairResult(transformation=current, fitness=fitness, inlier_rmse=rmse, weak_directions=weak)


def keep_guess_where_weak(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    transform: np.ndarray,
    guess: np.ndarray,
    distance: float,
    threshold: float,
    *,
    planar: bool = False,
) -> tuple[np.ndarray, int]:
    """Reset the translation of ``transform`` to ``guess``'s along weakly constrained directions.

    Point-to-plane ICP constrains translation only along the normals it matches: with
    ``H = mean(n n^T)`` over the target normals of the correspondences within ``distance``
    (eigenvalues summing to 1; 1/3 each for normals spread evenly, 0 along a direction no
    normal has a component in), each eigenvector with eigenvalue below ``threshold`` gets the
    guess's translation component back; rotation is kept (a solution remapping after Zhang,
    Kaess and Singh, ICRA 2016, applied once to the result). In 2D only the in-plane
    directions are examined.

    Returns:
        The ``(4, 4)`` transform and how many directions were reset.
    """
    from strep_core._open3d import o3d

    ev = o3d.pipelines.registration.evaluate_registration(source, target, distance, transform)
    corr = np.asarray(ev.correspondence_set)
    if len(corr) < 3 or not target.has_normals():
        return transform, 0
    dims = 2 if planar else 3
    normals = np.asarray(target.normals)[corr[:, 1], :dims]
    values, vectors = np.linalg.eigh(normals.T @ normals / len(normals))
    weak = vectors[:, values < threshold]
    if weak.shape[1] == 0:
        return transform, 0
    out = np.array(transform, dtype=np.float64)
    out[:dims, 3] -= weak @ (weak.T @ (out[:dims, 3] - np.asarray(guess)[:dims, 3]))
    return out, int(weak.shape[1])


def _icp_stage(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    start: np.ndarray,
    distance: float,
    *,
    kernel: float | None,
    criteria: Any,
    planar: bool,
    min_fitness: float,
) -> tuple[np.ndarray, float, float] | None:
    """One point-to-plane ICP stage at ``distance`` from ``start``: ``(transform, fitness,
    inlier RMSE)``, projected onto SE(2) when ``planar``; ``None`` when it matches no source
    point or fewer than ``min_fitness`` of them."""
    from strep_core._open3d import o3d

    reg = o3d.pipelines.registration
    estimation = (
        reg.TransformationEstimationPointToPlane()
        if kernel is None
        else reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=kernel * distance))
    )
    result = reg.registration_icp(source, target, distance, start, estimation, criteria)
    if result.fitness <= 0.0 or result.fitness < min_fitness:
        return None
    transform = np.asarray(result.transformation)
    return (project_planar(transform) if planar else transform), float(result.fitness), float(result.inlier_rmse)


def _best_yaw_start(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    offsets: tuple[float, ...],
    coarse: float,
    fine: float,
    *,
    criteria: Any,
    planar: bool,
    min_fitness: float,
    kernel: float | None,
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> tuple[np.ndarray, float, float] | None:
    """The best of ``init`` and ``init`` turned about ``axis`` by each yaw offset, each refined
    by one coarse ICP stage, scored by fitness (then RMSE) within ``fine`` (see `register_clouds`).

    Returns that candidate's coarse stage ``(transform, fitness, inlier RMSE)``, or ``None``
    when the stage fails from every start."""
    from strep_core._open3d import o3d

    best, best_key = None, (-1.0, 0.0)
    for yaw in (0.0, *offsets):
        turn = np.eye(4)
        turn[:3, :3] = g.so3_exp(np.asarray(axis, dtype=np.float64) * yaw)
        stage = _icp_stage(
            source,
            target,
            init @ turn,
            coarse,
            kernel=kernel,
            criteria=criteria,
            planar=planar,
            min_fitness=min_fitness,
        )
        if stage is None:
            continue
        ev = o3d.pipelines.registration.evaluate_registration(source, target, fine, stage[0])
        key = (round(float(ev.fitness), 3), -float(ev.inlier_rmse))
        if key > best_key:
            best, best_key = stage, key
    return best


def register_pair(
    source: np.ndarray,
    target: np.ndarray,
    init: np.ndarray | None,
    params: RegistrationParams,
    *,
    source_origin: np.ndarray | None = None,
    target_origin: np.ndarray | None = None,
) -> tuple[np.ndarray, PairResult]:
    """Register two frames given as point arrays, in the frames' own dimension.

    Args:
        source, target: ``(N, D)`` and ``(M, D)`` points, each in its local coordinates.
        init: ``(D+1, D+1)`` initial source -> target transform (``None``: identity).
        params: resolved settings (`resolve_params`, or built by hand).
        source_origin, target_origin: ``(D,)`` sensor positions (normals face them).

    Returns:
        ``(D+1, D+1)`` source -> target transform (exactly SE(2) in 2D) and the `PairResult`.
    """
    dim = np.asarray(source).shape[1]
    init4 = np.eye(4) if init is None else g.to_se3(init)
    with open3d_quiet(params.threads):
        src = prepare_frame(source, params, origin=source_origin)
        tgt = prepare_frame(target, params, origin=target_origin)
        res = register_with(src, tgt, init4, params)
    return from_se3(res.transformation, dim), res


def information_matrix(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, transform: np.ndarray, distance: float
) -> np.ndarray:
    """``(6, 6)`` information matrix of a source -> target ``(4, 4)`` alignment (Open3D's)."""
    from strep_core._open3d import o3d

    return np.asarray(
        o3d.pipelines.registration.get_information_matrix_from_point_clouds(source, target, distance, transform)
    )


def transform_cloud(cloud: o3d.geometry.PointCloud, transform: np.ndarray) -> o3d.geometry.PointCloud:
    """A transformed copy of a cloud (points and normals) by a ``(4, 4)`` transform."""
    from strep_core._open3d import o3d

    out = o3d.geometry.PointCloud(cloud)
    out.transform(np.asarray(transform, dtype=np.float64))
    return out


# --------------------------------------------------------------------------------------------
# Incremental ICP


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
        for k in range(1, k_frames):
            guess = g.relative(init3[k - 1], init3[k])
            if params.velocity_prior and pairs:
                guess = pairs[-1].transformation
            target = clouds[k - 1]
            if params.local_map > 1:
                target = _local_map(clouds, poses3, k, params)
            prior = _step_prior(pairs, stop=params.prior_stop)
            res = register_with(clouds[k], target, guess, params, prior=prior)
            pairs.append(res)
            poses3[k] = poses3[k - 1] @ res.transformation
            if params.planar:
                poses3[k] = project_planar(poses3[k])
            if on_frame is not None:
                on_frame(k, from_se3(poses3, seq.dim))
    poses = from_se3(poses3, seq.dim)
    return IncrementalResult(poses=poses, pairs=pairs, clouds=clouds, seconds=time.perf_counter() - started)


def _step_prior(pairs: list[PairResult], n: int = 5, *, stop: float = 0.0) -> np.ndarray | None:
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


def pair_report(pairs: list[PairResult]) -> tuple[dict[str, list[int]], dict[str, int]]:
    """A run's report of its ICP pairs (frame k: pair k-1 -> k): for its artifacts, the frames
    where ICP kept its guess (every stage failed) and where weakly constrained translation
    directions were reset to the guess; for its metrics, their counts ``icp_kept_guess`` and
    ``icp_weak_pairs``."""
    frames = {
        "kept_guess_frames": [k + 1 for k, p in enumerate(pairs) if p.kept_guess],
        "weak_direction_frames": [k + 1 for k, p in enumerate(pairs) if p.weak_directions],
    }
    kept, weak = frames["kept_guess_frames"], frames["weak_direction_frames"]
    counts = {"icp_kept_guess": len(kept), "icp_weak_pairs": len(weak)}
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


# --------------------------------------------------------------------------------------------
# Loop closures proposed and verified by the global scan matcher (2D)


@dataclass
class LoopClosure:
    """A verified loop closure: ``transformation`` ``(4, 4)`` maps frame ``j`` into frame ``i``."""

    i: int
    j: int
    transformation: np.ndarray
    score: float
    fitness: float


def global_loop_closures(
    clouds: list[Any],
    poses: np.ndarray,
    params: RegistrationParams,
    *,
    radius: float,
    min_gap: int,
    min_score: float,
    min_fitness: float,
    max_per_frame: int,
    every: int = 1,
    scales: tuple[float, ...] | None = None,
    max_turn: float = float(np.pi),
    on_frame: Callable[[int], None] | None = None,
) -> tuple[list[LoopClosure], int]:
    """Loop closures of a 2D sequence found by the global scan matcher (`strep_core.scanmatch`).

    For every ``every``-th frame j, the earlier frames i (``j - i >= min_gap``) whose estimated
    positions lie within ``radius`` of j's, nearest first, at most ``max_per_frame`` of them and no
    two within ``min_gap // 2`` frames of each other, are matched: frame j against frame i over
    every heading and ``params.global_match.window`` around the estimate's relative pose (so a
    chain that drifted by up to the window still closes), then refined by ICP from the match
    (``scales``). A candidate is kept when the matcher scores the refined pose at least
    ``min_score`` in both directions (j in i's field and i in j's: a scan that sees only part of
    the other cannot pass by overlapping a wall) and ICP matches ``min_fitness`` of j's points.
    The match searches every heading, but a loop whose relative heading differs from the chain's
    estimate by more than ``max_turn`` (radians) is rejected: a corridor looks the same after a
    half turn and a square room after a quarter turn, and a match that turns the chain by one of
    these is an ambiguous place rather than a correction of the chain's heading
    (docs/design/scan-matching.md, third part).

    Returns:
        The loop closures and the number of candidates tried.
    """
    from scipy.spatial import cKDTree

    if params.global_match is None or not params.planar or max_per_frame <= 0:
        return [], 0
    gm = dataclasses.replace(params.global_match, yaw_window=float(np.pi))  # a loop may face any way
    poses3 = g.to_se3(np.asarray(poses, dtype=np.float64))
    pts = [np.asarray(c.points)[:, :2] for c in clouds]
    positions = poses3[:, :2, 3]
    tree = cKDTree(positions)
    stages = (params.scales[1:] or params.scales) if scales is None else tuple(scales)
    spread = max(1, min_gap // 2)
    found: list[LoopClosure] = []
    tried = 0
    for j in range(1, len(clouds)):
        if j < min_gap or j % every:
            if on_frame is not None:
                on_frame(j)
            continue
        near = [i for i in tree.query_ball_point(positions[j], r=radius) if i <= j - min_gap]
        near.sort(key=lambda i: float(np.linalg.norm(positions[i] - positions[j])))
        chosen: list[int] = []
        for i in near:
            if len(chosen) >= max_per_frame:
                break
            if any(abs(i - c) < spread for c in chosen):
                continue
            chosen.append(i)
        for i in chosen:
            tried += 1
            guess = from_se3(g.relative(poses3[i], poses3[j])[None], 2)[0]
            matcher = ScanMatcher(pts[i], gm, center=guess[:2, 2])
            match = matcher.match(pts[j], guess)
            if match.score < min_score or float(g.rotation_angle(g.relative(guess, match.pose))) > max_turn:
                continue
            res = _register(clouds[j], clouds[i], g.to_se3(match.pose), params, stages, ())
            if res.kept_guess or res.fitness < min_fitness:
                continue
            pose2 = from_se3(res.transformation[None], 2)[0]
            if float(g.rotation_angle(g.relative(guess, pose2))) > max_turn:
                continue
            forward = matcher.evaluate(pts[j], pose2)
            backward = ScanMatcher(pts[j], gm, center=g.inverse(pose2)[:2, 2]).evaluate(pts[i], g.inverse(pose2))
            if min(forward, backward) < min_score:
                continue
            found.append(LoopClosure(i, j, res.transformation, min(forward, backward), res.fitness))
        if on_frame is not None:
            on_frame(j)
    return found, tried
