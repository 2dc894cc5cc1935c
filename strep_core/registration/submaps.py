"""Local SLAM of planar laser scans: each scan matched against a submap, not the previous scan.

After Cartographer's local SLAM (Hess et al., ICRA 2016) and Olson's correlative matching
(ICRA 2009), in this project's terms (measurements: docs/design/laser-slam.md):

* a *submap* is the union of a run of consecutive scans placed by their local estimates,
  voxelised at the search resolution; two are active at a time, overlapping by half, and one
  is finished (frozen) after `LaserSlamParams.submap_scans` scans, so the matching target is
  never a thin new submap;
* each scan is registered against the older active submap: the branch-and-bound search of
  `strep_core.scanmatch` within a window around the constant-velocity prediction (each heading
  paying its turn from the prediction or from stopping; a straight step held at least at the
  keyframe spacing where the log shows one), then a point-to-line Gauss-Newton refinement
  against the submap's points (`refine`);
* nothing unphysical: the window and the motion bounds come from the log itself (robust
  statistics of the accepted steps and turns); a match outside them or with a low score is
  *failed* and bridged at the prediction with a wide covariance; a match whose refinement
  leaves a direction unconstrained (a corridor) is *ambiguous*; every match records its
  verdict, score and covariance (`Match`).

Conventions: points ``(N, 2)`` in the sensor frame, poses ``(3, 3)`` SE(2) local -> world.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from strep_core import geometry as g
from strep_core.registration.motion_prior import (
    STRAIGHT,
    keyframe_cost,
    keyframe_spacing,
    keyframe_velocity,
    turn_cost,
    yaw_cost,
)
from strep_core.registration.params import point_spacing
from strep_core.scanmatch import ScanMatcher, ScanMatchParams
from strep_core.sequence import Sequence
from strep_core.voxels import first_per_cell

Verdict = Literal["accepted", "ambiguous", "failed"]


@dataclass(frozen=True)
class LaserSlamParams:
    """Settings of the local SLAM, in the sequence's unit (`derive_params` builds them).

    Attributes:
        resolution: finest cell of the search grid and voxel of the submaps.
        max_range: scan points beyond this range are not matched.
        window: initial translation search window (+-, each axis), before motion is known.
        yaw_window: initial heading window (+-, radians).
        submap_scans: scans per submap before it is finished.
        min_score: a match scoring below this share of the accepted median fails.
        peak_margin: a second peak (the prediction's own) within this score of the best, once
            each pays its turn away from the prediction, wins: the match is ambiguous.
        weak_score: a match below this share of the accepted median is cross-checked against
            the latest scan alone (an older part of the submap may alias it).
        bound_factor: motion bounds are this many times the 90th percentile of accepted motion.
        step_factor: the step bound's floor (half the initial window) is capped at this many
            times the 90th percentile of the accepted steps that moved (above one grid cell)
            without turning (under 10 degrees);
            the ground truth of all eight CARMEN logs stays within 2.55 times it.
        history: motion statistics over at most this many accepted matches.
        weak_ratio: a refinement whose weakest direction carries less than this share of the
            strongest's information is ambiguous.
        prior_weight, prior_scale: score lost at ``prior_scale`` from the predicted translation
            (the branch and bound's tie-break in corridors) and per radian squared of turn.
    """

    resolution: float
    max_range: float
    window: float
    yaw_window: float = float(np.pi)
    submap_scans: int = 20
    min_score: float = 0.5
    peak_margin: float = 0.05
    weak_score: float = 0.7
    bound_factor: float = 2.0
    step_factor: float = 3.0
    history: int = 500
    weak_ratio: float = 0.02
    prior_weight: float = 0.2
    prior_scale: float = 1.0


@dataclass
class Match:
    """One scan's registration: verdict, score (mean likelihood, 0 to 1), pose, and the
    covariance ``(3, 3)`` of its motion from the previous scan (x, y, theta in the scan's own frame)."""

    verdict: Verdict
    score: float
    pose: np.ndarray
    covariance: np.ndarray
    window: float = 0.0
    spun: bool = False  # failed, bridged at the prediction because its turn passed the bound


@dataclass
class Submap:
    """Scans (``scans``, their indices) in the world frame of the local SLAM; ``first`` is the
    scan index from which it takes scans."""

    first: int
    points: list[np.ndarray] = field(default_factory=list)
    scans: list[int] = field(default_factory=list)
    finished: bool = False
    _cloud: np.ndarray | None = None

    @property
    def count(self) -> int:
        return len(self.scans)

    @property
    def anchor(self) -> int:
        """The first scan inserted: loop closures are edges from it."""
        return self.scans[0]

    def insert(self, world_points: np.ndarray, k: int) -> None:
        self.points.append(world_points)
        self.scans.append(k)
        self._cloud = None

    def cloud(self, resolution: float, *, without: int | None = None) -> np.ndarray:
        """The submap's points, one per ``resolution`` cell (cached until the next insert);
        ``without``: leave that scan out (not cached; an active submap's own scans only)."""
        if without is not None:
            return _voxel_points(
                np.concatenate([pts for pts, k in zip(self.points, self.scans, strict=True) if k != without]),
                resolution,
            )
        if self._cloud is None:
            self._cloud = _voxel_points(np.concatenate(self.points), resolution)
            if self.finished:
                self.points = [self._cloud]  # a frozen submap keeps only its voxelised points
        return self._cloud


def _voxel_points(pts: np.ndarray, resolution: float) -> np.ndarray:
    """The first point of each ``resolution`` cell, in their order."""
    return pts[first_per_cell(pts, resolution)]


def derive_params(seq: Sequence) -> LaserSlamParams:
    """Settings from the data. The grid: 0.025 of the scale (median range, so metres and pixels
    alike), finer where the scans are denser (the median spacing of neighbouring points: 361-beam
    logs; whole belgioioso 0.775 -> 0.095 m, freiburg-campus 46 -> 22 m). Every range is used (a
    corridor's far end is what fixes the slide along it: aces[0:100] 6.4 m with ranges cut at
    their 95th percentile, 0.31 m uncut). The motion windows start wide (1.5 scales, every
    heading) and shrink to what the log shows (`_Motion`). docs/design/laser-slam.md."""
    scale = seq.scale()
    far = max((float(np.linalg.norm(f, axis=1).max()) for f in seq.frames if len(f)), default=scale)
    res = min(0.025 * scale, point_spacing(seq, max_frames=20))
    return LaserSlamParams(resolution=res, max_range=far, window=1.5 * scale, prior_scale=scale)


def refine(
    points: np.ndarray, tree: cKDTree, target: np.ndarray, normals: np.ndarray, pose: np.ndarray, dist: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """Point-to-line Gauss-Newton of ``points`` onto the target's lines from ``pose``.

    Returns ``(pose, information (3, 3), inlier share)``; the information is the normal
    matrix ``sum J^T J / sigma^2`` of the last step (x, y in the world frame, theta), so a
    corridor leaves its axis weak.
    """
    pose = pose.copy()
    info = np.zeros((3, 3))
    share = 0.0
    for it in range(8):
        d = dist if it < 4 else 0.5 * dist
        world = points @ pose[:2, :2].T + pose[:2, 2]
        dd, idx = tree.query(world, distance_upper_bound=d)
        ok = np.isfinite(dd)
        share = float(ok.mean())
        if ok.sum() < 6:
            break
        p, q, n = world[ok], target[idx[ok]], normals[idx[ok]]
        r = np.einsum("ij,ij->i", p - q, n)
        c = pose[:2, 2]
        jac = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * (p[:, 0] - c[0]) - n[:, 0] * (p[:, 1] - c[1])])
        w = 1.0 / (1.0 + (r / (0.5 * d)) ** 2)  # Cauchy weights
        h = (jac * w[:, None]).T @ jac
        b = (jac * w[:, None]).T @ r
        try:
            delta = -np.linalg.solve(h + 1e-9 * np.eye(3), b)
        except np.linalg.LinAlgError:
            break
        step = g.se2_from_xytheta(np.asarray(delta))
        # rotate about the current position: p' = R (p - c) + c + t
        rot = step[:2, :2]
        pose[:2, :2] = rot @ pose[:2, :2]
        pose[:2, 2] = c + step[:2, 2]
        sigma2 = max(float(np.sum(w * r * r) / max(w.sum(), 1e-9)), (0.05 * d) ** 2)
        info = h / sigma2
        if abs(delta[2]) < 1e-5 and np.hypot(delta[0], delta[1]) < 1e-4 * d:
            break
    return pose, info, share


def normals_2d(points: np.ndarray, tree: cKDTree, k: int = 6) -> np.ndarray:
    """Unit normals ``(N, 2)``: the smallest principal direction of each point's ``k`` neighbours."""
    k = min(k, len(points))
    _, idx = tree.query(points, k=k)
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, 0]


class _Motion:
    """Robust statistics of the accepted steps, turns and scores: the window and the bounds."""

    def __init__(self, params: LaserSlamParams) -> None:
        self.p = params
        self.steps: list[float] = []
        self.turns: list[float] = []
        self.scores: list[float] = []

    def add(self, step: float, turn: float) -> None:
        self.steps = [*self.steps, step][-self.p.history :]
        self.turns = [*self.turns, turn][-self.p.history :]

    def moving(self) -> list[float]:
        """The accepted steps that moved (over a grid cell) without turning (`STRAIGHT`)."""
        return [s for s, t in zip(self.steps, self.turns, strict=True) if s > self.p.resolution and t < STRAIGHT]

    def straight_step(self) -> float | None:
        """The keyframe spacing of the accepted straight steps so far (`keyframe_spacing`)."""
        return keyframe_spacing(self.moving())

    @property
    def known(self) -> bool:
        return len(self.steps) >= 10

    def bounds(self) -> tuple[float, float]:
        """``(step, turn)``: the largest plausible motion between two scans. Until 10 matches
        are accepted, the initial windows; then ``bound_factor`` times the 90th percentile of
        the accepted steps and turns, never below half the initial window or 45 degrees (a log
        that starts by turning in place has not shown its steps yet); that step floor is capped
        at ``step_factor`` times the 90th percentile of the steps that moved without turning (over
        a grid cell, under 10 degrees), once ten did."""
        if not self.known:
            return self.p.window, self.p.yaw_window
        step = max(self.p.bound_factor * float(np.percentile(self.steps, 90)), 0.5 * self.p.window)
        # the floor is for a log that has not moved yet: once ten steps moved (above a grid cell)
        # it never exceeds step_factor times their 90th percentile (freiburg-campus scan 1331: a
        # 9.1 m jump accepted under a 9.7 m floor, the robot moving 1.15 m). A step turning more
        # than 10 degrees is no evidence of speed: a laser off the axis moves while the robot
        # turns in place (intel's first 11 scans, 0.06 m at 30 degrees, capped the bound at 0.27 m
        # before a 1 m step; docs/design/laser-slam.md, round 5)
        moving = self.moving()
        if len(moving) >= 10:
            step = min(step, self.p.step_factor * float(np.percentile(moving, 90)))
        turn = max(self.p.bound_factor * float(np.percentile(self.turns, 90)) + np.radians(10.0), np.radians(45.0))
        return min(step, self.p.window), min(turn, self.p.yaw_window)


def local_slam(
    frames: list[np.ndarray],
    params: LaserSlamParams,
    *,
    start: np.ndarray | None = None,
    on_scan: Callable[[int, np.ndarray], None] | None = None,
    on_submap: Callable[[Submap], None] | None = None,
) -> tuple[np.ndarray, list[Match], list[Submap]]:
    """Register every scan against the active submap.

    Returns ``(poses (K, 3, 3), matches (one per scan; scan 0's is a fixed start), submaps)``.
    ``on_submap`` is called with each submap as it is finished (loop-closure search).
    """
    p = params
    res = p.resolution
    k_frames = len(frames)
    poses = np.zeros((k_frames, 3, 3))
    poses[0] = np.eye(3) if start is None else start
    matches = [Match("accepted", 1.0, poses[0], np.diag([1e-6, 1e-6, 1e-8]))]
    motion = _Motion(p)
    submaps: list[Submap] = [Submap(0)]
    velocity = np.eye(3)
    travel: np.ndarray | None = None  # the unit direction of the last long straight step
    last_ok = 0
    local = [_cap(f, p.max_range) for f in frames]

    def insert(k: int) -> None:
        world = g.apply(poses[k], local[k])
        for sm in submaps:
            if not sm.finished:
                sm.insert(world, k)
        active = [sm for sm in submaps if not sm.finished]
        if active[-1].count >= max(1, p.submap_scans // 2):
            submaps.append(Submap(k + 1))
        if active[0].count >= p.submap_scans:
            active[0].finished = True
            active[0].cloud(res)
            if on_submap is not None:
                on_submap(active[0])

    insert(0)
    for k in range(1, k_frames):
        target_map = next(sm for sm in submaps if not sm.finished and sm.count > 0)
        # after a scan that turned past the bound and was bridged at the prediction (whose heading
        # a stopped spin makes wrong), this scan is matched without the bridge (aces[155:255]
        # turned by -90 degrees 1.08 -> 0.11 m; docs/design/laser-slam.md, round 6)
        spun = k - last_ok == 2 and matches[k - 1].spun and target_map.count > 1
        target = target_map.cloud(res, without=k - 1 if spun else None)
        # constant velocity; in a keyframed log a straight step that slid short along a corridor
        # is not the speed (infinite-corridor[0:100] 3.78 -> 0.49 m; laser-slam.md, round 7)
        spacing = motion.straight_step()
        pred = poses[k - 1] @ keyframe_velocity(velocity, spacing, travel)
        step_bound, turn_bound = motion.bounds()
        # after failures the motion since the last accepted scan may be as many bounds long
        n = k - last_ok
        step_bound, turn_bound = n * step_bound, min(np.pi, n * turn_bound)
        recent = g.apply(poses[k - 1], local[k - 1])
        match = _match(local[k], target, pred, poses[last_ok], step_bound, turn_bound, p, motion, recent, spacing)
        poses[k] = match.pose
        matches.append(match)
        rel = g.relative(poses[k - 1], poses[k])
        if match.verdict != "failed":
            since = g.relative(poses[last_ok], poses[k])
            motion.add(float(np.hypot(*since[:2, 2])) / n, abs(float(np.arctan2(since[1, 0], since[0, 0]))) / n)
            velocity = rel
            length = float(np.hypot(*rel[:2, 2]))
            if spacing is not None and length >= 0.5 * spacing and abs(g.so2_angle(rel[:2, :2])) < STRAIGHT:
                travel = rel[:2, 2] / length
            last_ok = k
        insert(k)
        if on_scan is not None:
            on_scan(k, poses)
    return poses, matches, submaps


def _cap(points: np.ndarray, max_range: float) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)[:, :2]
    return pts[np.linalg.norm(pts, axis=1) <= max_range]


def _match(
    points: np.ndarray,
    target: np.ndarray,
    pred: np.ndarray,
    anchor: np.ndarray,
    step_bound: float,
    turn_bound: float,
    p: LaserSlamParams,
    motion: _Motion,
    recent: np.ndarray | None = None,
    spacing: float | None = None,
) -> Match:
    """Branch and bound within the bounds around ``pred``, refinement, verdict; ``anchor`` is
    the last accepted scan's pose and the bounds are on the motion since it; ``spacing``: the
    log's keyframe spacing (`_Motion.straight_step`), if it shows one."""
    res = p.resolution
    # the search covers exactly the bounds around the anchor; the prior leans to the prediction
    window = step_bound
    yaw_window = min(np.pi, turn_bound)
    sm_params = ScanMatchParams(
        window=window,
        resolution=res,
        yaw_window=yaw_window,
        max_range=p.max_range,
        max_points=200,
        prior_weight=p.prior_weight,
        prior_scale=p.prior_scale,
    )
    matcher = ScanMatcher(target, sm_params, center=anchor[:2, 2])
    # every heading pays its turn cost in the search itself, not only in the choice between two
    # peaks: a wrong heading far from both going on and stopping no longer wins on a few points
    # (belgioioso, acapulco at half rate: -97 and 113 degree turns; laser-slam.md, round 7)
    found = matcher.match(points, anchor, prior=pred[:2, 2], yaw_cost=yaw_cost(pred, anchor, p.prior_weight))
    tree = cKDTree(target)
    normals = normals_2d(target, tree)
    pose_a, info_a, _ = refine(points, tree, target, normals, found.pose, 3 * res)
    score_a = matcher.evaluate(points, pose_a)
    if score_a < found.score:
        pose_a, score_a = found.pose, found.score
    # the prediction's own basin: a second peak of the landscape when it differs from the best
    near = ScanMatchParams(
        window=0.25 * step_bound,
        resolution=res,
        yaw_window=float(np.radians(15.0)),
        max_range=p.max_range,
        max_points=200,
    )
    local_peak = ScanMatcher(target, near, center=pred[:2, 2]).match(points, pred)
    pose_b, info_b, _ = refine(points, tree, target, normals, local_peak.pose, 3 * res)
    score_b = matcher.evaluate(points, pose_b)
    apart = g.relative(pose_a, pose_b)
    gap = float(np.hypot(*apart[:2, 2]))
    verdict: Verdict = "accepted"
    pose, info, score = pose_a, info_a, score_a
    floor = p.min_score * (float(np.median(motion.scores)) if motion.scores else 0.6)
    two_peaks = gap > 2 * res or abs(float(np.arctan2(apart[1, 0], apart[0, 0]))) > np.radians(1.0)
    # two real peaks of about one height (a turn away from both going on and stopping costs):
    # steady motion decides (round 6, docs/design/laser-slam.md)
    cost_a, cost_b = (turn_cost(pred, anchor, pose, p.prior_weight) for pose in (pose_a, pose_b))
    if spacing is not None:  # and a straight step off the keyframe spacing (round 7)
        cost_a, cost_b = (
            c + keyframe_cost(anchor, pose, spacing, p.prior_weight) for c, pose in ((cost_a, pose_a), (cost_b, pose_b))
        )
    near = score_b - cost_b >= score_a - cost_a - p.peak_margin
    if two_peaks and score_b >= floor and near:
        verdict, pose, info, score = "ambiguous", pose_b, info_b, score_b
    sums: list[tuple[float, float]] = []
    latest: list[ScanMatcher] = []

    def on_latest(pose: np.ndarray) -> float:
        """The score of ``pose`` against the latest scan alone (its field built once)."""
        if not latest:
            latest.append(ScanMatcher(recent, sm_params, center=anchor[:2, 2]))
        return latest[0].evaluate(points, pose)

    def latest_sums() -> tuple[float, float]:
        """Each peak's score against the submap plus against the latest scan alone."""
        if not sums:
            sums.append((on_latest(pose_a) + score_a, on_latest(pose_b) + score_b))
        return sums[0]

    if recent is not None and score < p.weak_score * floor / p.min_score and verdict == "accepted":
        # a weak peak may alias an older part of the submap: the latest scan, which shares the
        # most of this view, must agree (docs/design/laser-slam.md, belgioioso scan 89)
        sum_a, sum_b = latest_sums()
        if sum_b > sum_a:
            verdict, pose, info, score = "ambiguous", pose_b, info_b, score_b
    rel = g.relative(anchor, pose)
    step = float(np.hypot(*rel[:2, 2]))
    turn = abs(float(np.arctan2(rel[1, 0], rel[0, 0])))
    wide = np.diag([step_bound**2, step_bound**2, turn_bound**2])
    # unphysical: bridged at the prediction; the refinement may turn past the searched bound by a
    # yaw step (aces scan 169: a -78.5 degree spin found at -80.0, refined to -80.2)
    spun = turn > turn_bound + sm_params.yaw_step
    if step > step_bound or spun:
        return Match("failed", score, pred.copy(), wide, window, spun=spun)
    if score < floor:  # a weak peak: the latest scan picks the bridge, free for the graph
        bridge = pose_b
        if recent is not None:
            sum_a, sum_b = latest_sums()
            if sum_a > sum_b:
                bridge = pose_a
            # a third candidate: the prediction's place at any heading within the bound (the
            # basin's +-15 degrees miss a turn that reversed; belgioioso scan 345 at 135 and
            # 225 degrees, bridged 2 m off: whole log 0.853 -> 0.070 m; laser-slam.md, round 10)
            turning = ScanMatchParams(
                window=0.25 * step_bound, resolution=res, yaw_window=yaw_window, max_range=p.max_range, max_points=200
            )
            found_c = ScanMatcher(target, turning, center=pred[:2, 2]).match(
                points, pred, yaw_cost=yaw_cost(pred, anchor, p.prior_weight)
            )
            pose_c, _, _ = refine(points, tree, target, normals, found_c.pose, 3 * res)
            if on_latest(pose_c) + matcher.evaluate(points, pose_c) > max(sum_a, sum_b):
                bridge = pose_c
        return Match("failed", score, bridge, wide, window)
    motion.scores = [*motion.scores, score][-p.history :]
    cov = _motion_covariance(info, pose, res)
    if verdict == "ambiguous":  # uncertain along the line between the two peaks
        cov = cov + _spread(pose_b, pose_a)
    else:
        eig = np.linalg.eigvalsh(info[:2, :2])
        if eig[0] < p.weak_ratio * max(eig[1], 1e-12):
            verdict = "ambiguous"
    return Match(verdict, score, pose, cov, window)


def _spread(chosen: np.ndarray, other: np.ndarray) -> np.ndarray:
    """``d d^T`` for ``d`` the motion ``(x, y, theta)`` from the chosen peak to the other, in the
    chosen peak's frame: translation and turn with one sign, so the pose graph can slide to the
    other peak at a Mahalanobis cost of 1 (round 5 fixed the turn's sign; docs/design/laser-slam.md)."""
    d = g.se2_to_xytheta(g.relative(chosen, other))
    return np.outer(d, d)


def _motion_covariance(info_world: np.ndarray, pose: np.ndarray, res: float) -> np.ndarray:
    """The refinement's covariance in the scan's own frame, floored at a grid cell."""
    floor = np.diag([(0.5 * res) ** 2, (0.5 * res) ** 2, np.radians(0.25) ** 2])
    cov = np.linalg.pinv(info_world + np.linalg.inv(np.diag([1e4, 1e4, 1e2])))
    rot = np.eye(3)
    rot[:2, :2] = pose[:2, :2].T
    return rot @ cov @ rot.T + floor
