"""Global SLAM of planar laser scans: loop closures against finished submaps, a robust graph.

After Cartographer's global SLAM and Karto: every few metres a scan is searched against the
finished submaps near its estimate (branch and bound, `strep_core.scanmatch`), within a radius
that grows with the uncertainty accumulated along the chain since the submap; a candidate is
verified (a high score, one peak: the refinement from the prediction must agree; no runner-up
elsewhere in the window as high, which a repeated corridor has) before it is used, and the
back end is robust to the wrong ones that remain: GTSAM's graduated non-convexity over the
loop factors, the chain's factors known inliers (measurements:
docs/design/laser-slam.md).

Conventions: poses ``(3, 3)`` SE(2) local -> world; covariances ``(3, 3)`` over (x, y, theta)
in the frame of the second pose of each edge.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from strep_core import geometry as g
from strep_core.registration.motion_prior import STRAIGHT, keyframe_spacing
from strep_core.registration.submaps import LaserSlamParams, Match, Submap, normals_2d, refine
from strep_core.scanmatch import ScanMatcher, ScanMatchParams


@dataclass(frozen=True)
class Edge:
    """A relative pose ``T_i^-1 T_j`` (``(3, 3)``) with its covariance, in node j's frame."""

    i: int
    j: int
    transform: np.ndarray
    covariance: np.ndarray
    score: float = 1.0
    loop: bool = False


@dataclass(frozen=True)
class StepPrior:
    """A soft prior on the distance between scans ``i`` and ``j``: ``length`` +- ``sigma``."""

    i: int
    j: int
    length: float
    sigma: float


@dataclass(frozen=True)
class LoopParams:
    """Loop-closure search (lengths in the sequence's unit).

    Attributes:
        every: a scan is searched after the chain travelled this far since the last one.
        radius: search radius before any uncertainty; it grows by 3 sigma of the chain's.
        max_radius: the radius's cap.
        min_gap: submaps whose scans end fewer than this many scans before are not searched.
        min_score: a closure scores at least this share of the chain's median score (0.85:
            freiburg-campus 3.6 -> 1.2 m, acapulco 0.56 -> 0.47 m against 0.9).
        candidates: the nearest finished submaps searched per scan. Six, not two: the nearest
            are often clutter or a distorted submap and the revisit lies farther
            (freiburg-campus 25.0 -> 1.2 m on one local chain, the cost bounded per scan;
            docs/design/laser-slam.md).
        passes: searches over the log, at most; each after the first starts from the graph's
            poses and searches only the (submap, scan) pairs whose guess moved by half the window
            or more (freiburg-campus 1.21 -> 0.415 m, intel 0.079 -> 0.076 m, no log worse;
            without that rule aces 0.131 -> 0.151 m and freiburg-079 257 s). The search stops at
            the first pass that finds no new closure: each pass's closures bring the next
            revisit into reach (infinite-corridor, scans 711-906 over 0-150: 1.02 -> 0.365 m
            with a third and fourth pass; docs/design/laser-slam.md, round 17).
        yaw_window: headings searched around the estimate's (+-; every heading, pi, found no
            more closures on freiburg-campus at 1.5 times the cost).
        neighbours: closures within this many searches of travel of each other check each
            other (`consistent`).
        runner_up: a closure's runner-up is the best pose farther than this many grid cells
            from it (4 field sigmas: off the best peak's shoulder); 0: no runner-up search.
            infinite-corridor whole, heading 0: wrong closures 46 -> 9 (docs/design/laser-slam.md,
            round 10).
        runner_margin: a runner-up that refines to another place scoring within this of the
            best makes the closure an alias, left out.
        search_floor: a closure's branch and bound prunes below this share of the score the
            closure must reach (it scores the reaching points only, which score about as high as
            all of them); the loop search is 2-3 times faster where most searches fail, every
            pose of the eight logs from identity is as without it, and one closure in about 1,000
            (a peak on the window's edge refined out of it) is lost (docs/design/laser-slam.md,
            rounds 14-15).
    """

    every: float
    radius: float
    max_radius: float
    min_gap: int
    min_score: float = 0.85
    candidates: int = 6
    yaw_window: float = float(np.radians(30.0))
    passes: int = 8
    neighbours: float = 20.0
    runner_up: float = 8.0
    runner_margin: float = 0.05
    search_floor: float = 0.8


def loop_params(slam: LaserSlamParams, scale: float) -> LoopParams:
    """Defaults from the data's scale and the submap size."""
    return LoopParams(every=1.0 * scale, radius=1.0 * scale, max_radius=3.0 * scale, min_gap=2 * slam.submap_scans)


def chain_edges(poses: np.ndarray, matches: Sequence[Match]) -> list[Edge]:
    """Consecutive-scan edges from the local SLAM (failed matches keep their wide covariance)."""
    edges = []
    for k in range(1, len(poses)):
        rel = g.relative(poses[k - 1], poses[k])
        edges.append(Edge(k - 1, k, rel, matches[k].covariance, matches[k].score))
    return edges


def spacing_priors(poses: np.ndarray, matches: Sequence[Match], resolution: float) -> list[StepPrior]:
    """In a keyframed log, each ambiguous straight step shorter than the spacing held softly at it.

    The spacing and its spread come from the chain's accepted straight steps (`keyframe_spacing`;
    the spread 1.4826 times their median absolute deviation, at least a grid cell). An ambiguous
    step is one whose landscape has two peaks or a weak axis: along a corridor it slides short
    (infinite-corridor scan 46: 0.474 m for 1.123). A log keeps a scan per distance travelled,
    a least distance, so a longer step is left alone (held too, freiburg-campus whole went 0.479
    -> 0.542 m). The prior goes into the graph only, so the chain, its submaps and the loop
    search are as before (a fused chain, round 11 (n), sent freiburg-campus to 27 m;
    docs/design/laser-slam.md, round 13)."""
    rel = g.relative(poses[:-1], poses[1:])  # step k - 1 -> k at index k - 1
    step = np.hypot(rel[:, 0, 2], rel[:, 1, 2])
    turn = np.abs(g.so2_angle(rel[:, :2, :2]))
    accepted = np.array([m.verdict == "accepted" for m in matches[1:]], dtype=bool)
    moving = step[accepted & (turn < STRAIGHT) & (step > resolution)]
    spacing = keyframe_spacing(moving)
    if spacing is None:
        return []
    sigma = max(1.4826 * float(np.median(np.abs(moving - spacing))), resolution)
    return [
        StepPrior(k - 1, k, spacing, sigma)
        for k in range(1, len(poses))
        if matches[k].verdict == "ambiguous" and turn[k - 1] < STRAIGHT and step[k - 1] < spacing
    ]


def _travelled(poses: np.ndarray) -> np.ndarray:
    """``(K,)`` distance travelled along the chain up to each scan."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :2, 2], axis=0), axis=1))])


def _chain_variance(matches: Sequence[Match]) -> np.ndarray:
    """``(K,)`` the chain's translation variance summed up to each scan (a bridged failure's
    wide covariance widens it): the variance between two scans is the difference."""
    return np.concatenate([[0.0], np.cumsum([np.trace(m.covariance[:2, :2]) for m in matches[1:]])])


def search_loops(
    frames: Sequence[np.ndarray],
    poses: np.ndarray,
    matches: Sequence[Match],
    submaps: Sequence[Submap],
    slam: LaserSlamParams,
    params: LoopParams,
    *,
    estimates: np.ndarray | None = None,
    searched: dict[tuple[int, int], np.ndarray] | None = None,
    on_scan: Callable[[int], None] | None = None,
) -> tuple[list[Edge], int]:
    """Loop-closure edges (anchor scan of a submap -> scan) and the number of searches tried.

    ``poses`` are the local SLAM's (the submaps' frame); the uncertainty between two scans is
    the sum of the chain's translation variances between them, so a bridged failure widens it.
    ``estimates``: poses after a graph (a second pass): the candidates are the submaps nearest
    there and each guess is the estimated relative pose from the submap's anchor.
    ``searched``: (submap, scan) -> guess of the searches so far, filled in; a pair whose new
    guess lies within half the window of its last one is not searched again.
    """
    res = slam.resolution
    finished = [sm for sm in submaps if sm.finished]
    if not finished:
        return [], 0
    var = _chain_variance(matches)
    est = poses if estimates is None else estimates
    centres = np.array([sm.cloud(res).mean(0) for sm in finished])
    if estimates is not None:  # each centroid carried into the estimates' frame by its anchor's correction
        centres = np.array(
            [
                g.apply(est[sm.anchor] @ np.linalg.inv(poses[sm.anchor]), c[None])[0]
                for sm, c in zip(finished, centres, strict=True)
            ]
        )
    ends = np.array([sm.scans[-1] for sm in finished])
    tree = cKDTree(centres)
    scores = [m.score for m in matches if m.verdict == "accepted"]
    floor = params.min_score * (float(np.median(scores)) if scores else 0.8)
    edges: list[Edge] = []
    tried = 0
    travelled = _travelled(poses)
    last = -np.inf
    cache: dict[int, tuple[cKDTree, np.ndarray]] = {}
    for k in range(len(poses)):
        if travelled[k] - last < params.every:
            continue
        last = travelled[k]
        if on_scan is not None:
            on_scan(k)
        pos = est[k][:2, 2]
        near = tree.query_ball_point(pos, params.max_radius + 0.5 * params.max_radius)
        found: list[tuple[Edge, Callable[[], bool]]] = []
        near = [s for s in near if ends[s] <= k - params.min_gap]
        near.sort(key=lambda s: float(np.linalg.norm(centres[s] - pos)))
        for s in near[: params.candidates]:
            sm = finished[s]
            sigma = float(np.sqrt(max(var[k] - var[sm.anchor], 0.0)))
            radius = min(params.max_radius, params.radius + 3 * sigma)
            if np.linalg.norm(centres[s] - pos) > radius + params.max_radius:
                continue
            guess = poses[k] if estimates is None else poses[sm.anchor] @ g.relative(est[sm.anchor], est[k])
            if searched is not None:
                before = searched.get((sm.first, k))
                if before is not None:
                    moved = g.relative(before, guess)
                    turn = abs(float(np.arctan2(moved[1, 0], moved[0, 0])))
                    if np.hypot(*moved[:2, 2]) < 0.5 * radius and turn < 0.5 * params.yaw_window:
                        continue
                searched[(sm.first, k)] = guess
            tried += 1
            closed = _close(frames[k], guess, sm, poses[sm.anchor], k, radius, slam, cache, params, floor)
            if closed is not None and closed[0].score >= floor:
                found.append(closed)
        # the best-scoring closure that is no alias (the runner-up test, the dearest, runs on the
        # candidates in order of score until one passes: about one a scan)
        for edge, aliased in sorted(found, key=lambda c: -c[0].score):
            if not aliased():
                edges.append(edge)
                break
    return edges, tried


def _close(
    points: np.ndarray,
    guess: np.ndarray,
    sm: Submap,
    anchor: np.ndarray,
    k: int,
    radius: float,
    slam: LaserSlamParams,
    cache: dict[int, tuple[cKDTree, np.ndarray]],
    loop: LoopParams,
    floor: float = 0.0,
) -> tuple[Edge, Callable[[], bool]] | None:
    """One scan against one finished submap; ``None`` unless one clear peak, else the closure
    and its runner-up test (`_aliased`, run on demand). ``floor``: the score a closure needs;
    the branch and bound prunes below ``loop.search_floor`` of it, and finding nothing there is no
    closure (docs/design/laser-slam.md, round 14)."""
    res = slam.resolution
    yaw_window = loop.yaw_window
    target = sm.cloud(res)
    pts = np.asarray(points, dtype=np.float64)[:, :2]
    params = ScanMatchParams(
        window=radius, resolution=res, yaw_window=yaw_window, max_range=slam.max_range, max_points=120
    )
    matcher = ScanMatcher(target, params, center=guess[:2, 2])
    # the search's grids span the scan's reach: points that cannot land on the submap from any
    # pose in the window score nothing anywhere, so the branch and bound leaves them out (the
    # scores below count every point; docs/design/laser-slam.md)
    reach = np.linalg.norm(target - guess[:2, 2], axis=1).max() + np.sqrt(2) * radius + 3 * params.field_sigma
    reaching = pts[np.linalg.norm(pts, axis=1) <= reach]
    found = matcher.match(reaching, guess, at_least=loop.search_floor * floor)
    if floor > 0 and found.score == 0:
        return None
    found = dataclasses.replace(found, score=matcher.evaluate(pts, found.pose))
    if sm.first not in cache:
        tree = cKDTree(target)
        cache[sm.first] = (tree, normals_2d(target, tree))
    tree, normals = cache[sm.first]
    pose, info, _ = refine(pts, tree, target, normals, found.pose, 3 * res)
    score = matcher.evaluate(pts, pose)
    if score < found.score:
        pose, score = found.pose, found.score
    # one peak: refined from the prediction, a pose elsewhere must score clearly lower
    other, _, _ = refine(pts, tree, target, normals, guess, 3 * res)
    if (
        np.linalg.norm(other[:2, 2] - pose[:2, 2]) > 2 * res
        and matcher.evaluate(pts, other) >= score - slam.peak_margin
    ):
        return None
    eig = np.linalg.eigvalsh(info[:2, :2])
    if eig[0] < slam.weak_ratio * max(eig[1], 1e-12):  # a corridor: no closure along its axis
        return None
    rel = g.relative(anchor, pose)
    floor = np.diag([(0.5 * res) ** 2, (0.5 * res) ** 2, np.radians(0.25) ** 2])
    cov = np.linalg.pinv(info + np.diag([1e-6, 1e-6, 1e-6])) + floor
    rot = np.eye(3)
    rot[:2, :2] = pose[:2, :2].T
    edge = Edge(sm.anchor, k, rel, rot @ cov @ rot.T, score, loop=True)
    if loop.runner_up <= 0:
        return edge, lambda: False
    return edge, lambda: _aliased(matcher, reaching, pts, pose, score, guess, tree, target, normals, res, loop)


def _aliased(
    matcher: ScanMatcher,
    reaching: np.ndarray,
    pts: np.ndarray,
    pose: np.ndarray,
    score: float,
    guess: np.ndarray,
    tree: cKDTree,
    target: np.ndarray,
    normals: np.ndarray,
    res: float,
    loop: LoopParams,
) -> bool:
    """Whether the best place off the closure's peak scores about as high (Olson's ambiguity
    test): the branch and bound again with the peak's disc left out, the runner-up refined."""
    second = matcher.match(reaching, guess, exclude=(pose[:2, 2], loop.runner_up * res))
    if second.score <= 0:
        return False
    other, _, _ = refine(pts, tree, target, normals, second.pose, 3 * res)
    s2 = max(matcher.evaluate(pts, other), matcher.evaluate(pts, second.pose))
    return bool(np.linalg.norm(other[:2, 2] - pose[:2, 2]) > 2 * res and s2 >= score - loop.runner_margin)


def consistent(
    loops: Sequence[Edge], poses: np.ndarray, matches: Sequence[Match], slam: LaserSlamParams, params: LoopParams
) -> list[Edge]:
    """The closures that agree with their neighbours (pairwise consistency over the chain).

    Closures a and b check each other when their scans lie within ``params.neighbours``
    searches of travel (``params.every`` each) and their anchors within twice that. They agree
    when the cycle they close with the chain, ``Z_a^-1 (T_ia^-1 T_ib) Z_b`` against ``T_ka^-1
    T_kb``, shuts within ten grid cells plus three sigma of the chain's and both closures'
    translation uncertainty. The closure with the most disagreements over agreements is dropped,
    then the next, until each one left agrees at least as often as it disagrees; one with no
    neighbour stays for GNC to judge. Along a repeated corridor the wrong closures of a revisit
    disagree with the right ones: infinite-corridor turned by 30 degrees 2.14 -> 0.80 m
    (docs/design/laser-slam.md, round 8). ``poses``: the local SLAM's.
    """
    n = len(loops)
    if n < 2:
        return list(loops)
    travelled = _travelled(poses)
    var = _chain_variance(matches)
    reach = params.neighbours * params.every
    floor = (10 * slam.resolution) ** 2
    order = sorted(range(n), key=lambda a: travelled[loops[a].j])
    balance = np.zeros(n, dtype=np.int64)  # agreements minus disagreements
    votes: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for x, a in enumerate(order):
        ea = loops[a]
        back = np.linalg.inv(ea.transform)
        for b in (order[y] for y in range(x + 1, n)):  # no copy of the tail: linear in closures
            eb = loops[b]
            if travelled[eb.j] - travelled[ea.j] > reach:
                break
            if abs(travelled[ea.i] - travelled[eb.i]) > 2 * reach:
                continue
            cycle = g.relative(
                g.relative(poses[ea.j], poses[eb.j]), back @ g.relative(poses[ea.i], poses[eb.i]) @ eb.transform
            )
            sigma2 = abs(var[ea.j] - var[eb.j]) + abs(var[ea.i] - var[eb.i])
            sigma2 += np.trace(ea.covariance[:2, :2]) + np.trace(eb.covariance[:2, :2])
            vote = 1 if float(np.hypot(*cycle[:2, 2])) ** 2 < floor + 9 * sigma2 else -1
            votes[a].append((b, vote))
            votes[b].append((a, vote))
            balance[a] += vote
            balance[b] += vote
    alive = np.ones(n, dtype=bool)
    while True:
        live = np.flatnonzero(alive)
        worst = live[int(np.argmin(balance[live]))]
        if balance[worst] >= 0:
            break
        alive[worst] = False
        for b, vote in votes[worst]:
            balance[b] -= vote
    return [e for e, keep in zip(loops, alive, strict=True) if keep]


def optimise(
    poses: np.ndarray, edges: Sequence[Edge], *, priors: Sequence[StepPrior] = (), robust: bool = True
) -> tuple[np.ndarray, int]:
    """Least squares over SE(2) with GTSAM; loop edges under graduated non-convexity.

    ``priors``: soft distances between scans (`spacing_priors`), known inliers like the chain.
    Returns ``(poses (K, 3, 3), loop edges kept as inliers)``; node 0 stays where it is.
    """
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, pose in enumerate(poses):
        values.insert(k, _pose2(pose))
    graph.add(gtsam.PriorFactorPose2(0, _pose2(poses[0]), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))))
    known: list[int] = [0]
    loop_index: list[int] = []
    for e in edges:
        noise = gtsam.noiseModel.Gaussian.Covariance(_spd(e.covariance))
        graph.add(gtsam.BetweenFactorPose2(e.i, e.j, _pose2(e.transform), noise))
        (loop_index if e.loop else known).append(graph.size() - 1)
    for p in priors:
        graph.add(gtsam.RangeFactorPose2(p.i, p.j, p.length, gtsam.noiseModel.Isotropic.Sigma(1, p.sigma)))
        known.append(graph.size() - 1)
    if robust and loop_index:
        gnc = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
        gnc.setKnownInliers(known)
        gnc.setVerbosityGNC(gtsam.GncLMParams.Verbosity.SILENT)
        opt = gtsam.GncLMOptimizer(graph, values, gnc)
        result = opt.optimize()
        weights = np.asarray(opt.getWeights())
        kept = int((weights[loop_index] > 0.5).sum())
    else:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        kept = len(loop_index)
    out = np.stack([_matrix(result.atPose2(k)) for k in range(len(poses))])
    return out, kept


def _spd(cov: np.ndarray) -> np.ndarray:
    cov = 0.5 * (cov + cov.T)
    w, v = np.linalg.eigh(cov)
    return (v * np.maximum(w, 1e-12)) @ v.T


def _pose2(pose: np.ndarray) -> Any:
    import gtsam

    return gtsam.Pose2(float(pose[0, 2]), float(pose[1, 2]), float(np.arctan2(pose[1, 0], pose[0, 0])))


def _matrix(p: Any) -> np.ndarray:
    return g.se2_from_xytheta(np.array([p.x(), p.y(), p.theta()]))
