"""Pairwise point-to-plane ICP of prepared clouds, coarse to fine, with the optional guards.

A pairwise result ``T`` maps *source* coordinates into *target* coordinates:
``p_target = T p_source``; with world poses ``P_s, P_t``: ``T = P_t^-1 P_s``
(``geometry.relative(P_t, P_s)``). Open3D's *legacy* pipeline is used: its tensor API is about
30x slower on CPU.

`icp_pair` is the one entry point for prepared clouds (every setting from `RegistrationParams`);
`align_frames` does the same for two frames given as point arrays. What the settings do:

* ``scales``: one ICP stage per multiplier of ``max_correspondence``, in order; a stage that
  matches fewer than ``min_fitness`` of the source points (or none) is discarded with the stages
  after it, and the transform stays where the previous stage left it (the guess if it is the
  first): this stops the rare runaway of point-to-plane ICP on a few degenerate matches; in 3D
  a failed point-to-plane stage is first retried point-to-point from the same start;
* ``kernel``: Tukey robust-kernel width as a fraction of each stage's distance (``None``: L2);
* ``yaw_search``: yaw offsets (about the source's sensor, axis ``yaw_axis``) added to the guess
  as extra starts of the coarsest stage; the best start goes on: in 3D the lowest trimmed
  distance (`trimmed_distance`: the closest half of the matches both ways), in 2D the most
  source points matched within the finest distance (ties: the lower RMSE). Point-to-plane ICP
  converges only from within about 10 degrees; laser keyframes turn by up to 20 to 30; in 3D
  the starts may run on coarser copies of the clouds (``search_voxel``) and turn about the axis
  refined by the source's horizontal normals (``yaw_refine``): a LiDAR (docs/design/lidar.md);
* ``degeneracy``: after the last stage, translation along directions the matched normals barely
  constrain returns to the guess's (`keep_guess_where_weak`); 0: off;
* ``correlative`` (2D): the stages also run from a correlative scan match around the guess
  (`strep_core.correlative`), which wins when it matches more source points (by over 0.01);
* ``global_match`` (2D): the stages also run from the global scan matcher's best pose
  (`strep_core.scanmatch`: every heading, +-1.5 s, a prior on the last steps); when that lands
  in another basin than ICP from the guess, the higher matcher score wins.

Each `PairResult` says whether ICP failed and kept its guess and how many directions were reset.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from strep_core import geometry as g
from strep_core.correlative import correlative_match
from strep_core.errors import RegistrationError
from strep_core.registration.clouds import from_se3, open3d_quiet, prepare_frame, project_planar
from strep_core.registration.params import RegistrationParams
from strep_core.scanmatch import ScanMatcher

if TYPE_CHECKING:  # pragma: no cover
    from strep_core._open3d import o3d


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
        verdict: set by the chain (`strep_core.registration.chain`): ``accepted``;
            ``ambiguous`` (a translation direction weakly constrained); ``failed`` (ICP kept its
            guess, or a step past the log's motion bound, bridged at the guess).
        covariance: set by the chain: ``(D(D+1)/2, D(D+1)/2)`` over the motion's translation then
            rotation (x, y, theta in 2D), in the target's frame; ``None`` until then.
    """

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    kept_guess: bool = False
    weak_directions: int = 0
    verdict: str = "accepted"
    covariance: np.ndarray | None = None


def icp_pair(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    params: RegistrationParams,
    *,
    scales: tuple[float, ...] | None = None,
    yaw_search: bool = True,
    prior: np.ndarray | None = None,
) -> PairResult:
    """Point-to-plane ICP of prepared clouds (`prepare_frame`; ``target`` needs normals), coarse to
    fine, every setting from ``params`` (what each does: the module docstring).

    Args:
        source, target: Open3D clouds in 3D (``z = 0`` for 2D frames).
        init: ``(4, 4)`` initial source -> target transform.
        params: resolved settings (`resolve_params`, or built by hand).
        scales: overrides ``params.scales``.
        yaw_search: ``False`` starts from ``init`` alone, without the yaw search or the
            correlative and global starts (e.g. for loop closures).
        prior: ``(4, 4)`` expected motion for the global matcher's prior (`incremental_icp`).
    """
    stages = params.scales if scales is None else tuple(scales)
    first = _icp_stages(source, target, init, params, stages, params.yaw_search if yaw_search else ())
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
        other = _icp_stages(source, target, g.to_se3(found.pose), params, stages, ())
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
    second = _icp_stages(source, target, g.to_se3(start), params, stages, ())
    fit = [evaluate(source, target, fine, r.transformation).fitness for r in (best, second)]
    return second if fit[1] > fit[0] + 0.01 else best


def _icp_stages(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    params: RegistrationParams,
    scales: tuple[float, ...],
    yaw_search: tuple[float, ...],
) -> PairResult:
    """The ICP stages ``scales`` from ``init`` (after the yaw search, when ``yaw_search`` has
    offsets) and the weak-direction guard: `icp_pair` without the correlative start."""
    from strep_core._open3d import o3d

    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=int(params.iterations)
    )
    if not scales:
        raise RegistrationError("ICP needs at least one scale")
    planar, d = params.planar, params.max_correspondence
    current = project_planar(init) if planar else np.asarray(init, dtype=np.float64)
    guess, fitness, rmse = current, 0.0, 0.0
    stages = tuple(scales)
    if yaw_search:
        # the search runs the coarsest stage from every start: go on from its best result
        best = _best_yaw_start(source, target, current, yaw_search, d * scales[0], d * min(scales), params, criteria)
        if best is None:  # the coarsest stage failed from every start, ``init`` included
            return PairResult(transformation=current, fitness=0.0, inlier_rmse=0.0, kept_guess=True)
        (current, fitness, rmse), stages = best, stages[1:]
    moved = bool(yaw_search)
    for scale in stages:
        stage = _icp_stage(source, target, current, d * scale, params, criteria)
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
    corr = correspondences(source, target, transform, distance)
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


def correspondences(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, transform: np.ndarray, distance: float
) -> np.ndarray:
    """``(M, 2)`` (source index, target index) of each source point, moved by ``transform``,
    whose nearest target point lies within ``distance`` (Open3D's own matching)."""
    from strep_core._open3d import o3d

    ev = o3d.pipelines.registration.evaluate_registration(source, target, distance, transform)
    return np.asarray(ev.correspondence_set, dtype=np.int64).reshape(-1, 2)


def _icp_stage(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    start: np.ndarray,
    distance: float,
    params: RegistrationParams,
    criteria: Any,
) -> tuple[np.ndarray, float, float] | None:
    """One point-to-plane ICP stage at ``distance`` from ``start``: ``(transform, fitness,
    inlier RMSE)``, projected onto SE(2) when planar; ``None`` when it matches no source
    point or fewer than ``params.min_fitness`` of them."""
    from strep_core._open3d import o3d

    kernel = params.kernel

    reg = o3d.pipelines.registration
    estimation = (
        reg.TransformationEstimationPointToPlane()
        if kernel is None
        else reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=kernel * distance))
    )
    result = reg.registration_icp(source, target, distance, start, estimation, criteria)
    if not params.planar and (result.fitness <= 0.0 or result.fitness < params.min_fitness):
        # Open3D's point-to-plane solve has no damping: a level camera that sees only walls leaves
        # its vertical move unconstrained and the first step runs away; point-to-point cannot
        # (docs/design/profiles.md, "Turning depth cameras")
        result = reg.registration_icp(
            source, target, distance, start, reg.TransformationEstimationPointToPoint(), criteria
        )
    if result.fitness <= 0.0 or result.fitness < params.min_fitness:
        return None
    transform = np.asarray(result.transformation)
    return (project_planar(transform) if params.planar else transform), float(result.fitness), float(result.inlier_rmse)


def _best_yaw_start(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    offsets: tuple[float, ...],
    coarse: float,
    fine: float,
    params: RegistrationParams,
    criteria: Any,
) -> tuple[np.ndarray, float, float] | None:
    """The best of ``init`` and ``init`` turned about ``params.yaw_axis`` by each yaw offset, each
    refined by one coarse ICP stage, scored in 3D by `trimmed_distance` (lowest wins), in 2D by
    fitness within ``fine`` (then RMSE).

    In 3D fitness picked the wrong start on turns: a camera turned by 30 degrees shares half its
    view, and sliding it half-way back keeps as many points matched; the trimmed distance is lowest
    at the turn. A laser scan overlaps its neighbour far more, and there the trimmed distance lost
    two CARMEN windows that fitness registers (docs/design/profiles.md, "Turning depth cameras").

    Returns that candidate's coarse stage ``(transform, fitness, inlier RMSE)``, or ``None``
    when the stage fails from every start."""
    from scipy.spatial import cKDTree

    from strep_core._open3d import o3d

    axis = np.asarray(params.yaw_axis, dtype=np.float64)
    if not params.planar:
        if params.yaw_refine > 0 and source.has_normals():
            from strep_core.registration.lidar import refine_axis

            axis = refine_axis(np.asarray(source.normals), axis, float(np.degrees(params.yaw_refine)))
        if params.search_voxel is not None:  # the starts on coarser copies (docs/design/lidar.md)
            source, target = (_coarser(c, params.search_voxel) for c in (source, target))
        # the trimmed distance's inputs, once for every start
        src_pts, tgt_pts = np.asarray(source.points), np.asarray(target.points)
        tree = cKDTree(tgt_pts)

    def starts(yaws: tuple[float, ...]) -> tuple[tuple[np.ndarray, float, float] | None, tuple[float, float]]:
        best, best_score = None, (np.inf, 0.0)
        for yaw in yaws:
            turn = np.eye(4)
            turn[:3, :3] = g.so3_exp(axis * yaw)
            stage = _icp_stage(source, target, init @ turn, coarse, params, criteria)
            if stage is None:
                continue
            if params.planar:
                ev = o3d.pipelines.registration.evaluate_registration(source, target, fine, stage[0])
                score = (-round(float(ev.fitness), 3), float(ev.inlier_rmse))
            else:
                score = (trimmed_distance(src_pts, tgt_pts, stage[0], target_tree=tree), 0.0)
            if score < best_score:
                best, best_score = stage, score
        return best, best_score

    tried = (0.0, *offsets)
    best, best_score = starts(tried)
    cell = params.search_voxel or params.voxel or 0.0
    if not params.planar and params.yaw_verify > 0 and offsets and best_score[0] > params.yaw_verify * cell:
        # no start matched as a right match does: every other heading, at the search's step
        step = abs(offsets[0])
        rest = tuple(
            float(y)
            for y in np.arange(-np.pi, np.pi - 1e-9, step)
            if min(abs(np.angle(np.exp(1j * (y - t)))) for t in tried) > 1e-6
        )
        other, other_score = starts(rest)
        if other is not None and other_score < best_score:
            best = other
    return best


def _coarser(cloud: o3d.geometry.PointCloud, voxel: float) -> o3d.geometry.PointCloud:
    """``cloud`` downsampled to ``voxel`` (normals averaged per voxel, then unit length)."""
    out = cloud.voxel_down_sample(voxel)
    if out.has_normals():
        out.normalize_normals()
    return out if len(out.points) >= 3 else cloud


def trimmed_distance(
    source: np.ndarray, target: np.ndarray, transform: np.ndarray, keep: float = 0.5, *, target_tree: Any = None
) -> float:
    """Symmetric trimmed nearest-neighbour distance of ``source`` moved by ``transform`` and
    ``target``: the mean of each side's closest ``keep`` fraction of distances, averaged over
    both sides. The same criterion as the trimmed Chamfer kernel of the learned methods
    (`strep_core.losses`), which has its minimum at the true turn of half-overlapping views.
    ``target_tree``: a `scipy.spatial.cKDTree` of ``target``, to reuse over several transforms."""
    from scipy.spatial import cKDTree

    moved = g.apply(transform, source)
    tree = cKDTree(target) if target_tree is None else target_tree
    out = 0.0
    for dist in (tree.query(moved)[0], cKDTree(moved).query(target)[0]):
        n = max(1, int(len(dist) * keep))
        out += float(np.partition(dist, n - 1)[:n].mean())
    return out / 2


def align_frames(
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
        res = icp_pair(src, tgt, init4, params)
    return from_se3(res.transformation, dim), res
