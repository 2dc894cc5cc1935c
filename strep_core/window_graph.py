"""Loops across windows: the joined windows' chain and its revisits as one pose graph (issue 33).

Joined window by window (`strep_core.windows`), a long sequence carries each window's slow bend
on through every later join: 1,024 frames end 6.6-12.9 px off while the windows alone are 0.2-
4.7 px (docs/design/long-scratch.md). The revisits that would correct this lie across windows,
beyond the refinement's Chamfer reach, so they are closed here, before it:

1. **Chain.** One edge per consecutive pair of frames: the relative pose of the window in which the
   pair lies most centrally (a window's chain ends are its weakest part). Its noise is measured on
   the data: the spread of the two windows' relative poses on the frames they share, widened by
   `CHAIN_WIDEN` (the windows' errors are biased, not white: a bend accumulates).
2. **Loops.** Every `LOOP_EVERY`-th frame j against the `LOOP_PER_FRAME` nearest earlier frames i
   (``j - i >= LOOP_GAP``, within `LOOP_RADIUS` median steps of the current estimate): a trimmed
   point-to-point ICP of j's points against the submap of i and its `SUBMAP_HALF` neighbours each
   side. Kept where its residual is at most `LOOP_RESIDUAL` times the chain's own (a frame
   against the submap of the frames before it); its covariance is the fit's (residual variance
   times the inverse of its normal matrix).
3. **Graph.** GTSAM least squares with graduated non-convexity over the loops
   (`registration.laser_graph.optimise`), the chain's edges known inliers; then the loop search
   once more from the graph's poses (`LOOP_PASSES`). The laser logs' search repeats until a pass
   finds nothing new (`LoopParams.passes`, round 17); these windows keep two passes, not measured
   with more.

Planar sequences only (GTSAM's Pose2); 3D windows are joined as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from strep_core import geometry as g
from strep_core import metrics
from strep_core.registration.laser_graph import Edge, optimise

# All chosen on the windows of 1,024-frame seeds 0 and 2, confirmed on seeds 1 and 3
# (docs/design/long-scratch.md, "Loops across windows").
CHAIN_WIDEN = 10.0
LOOP_EVERY = 2
LOOP_PER_FRAME = 3
LOOP_GAP = 64
LOOP_RADIUS = 20.0  # median steps
LOOP_RESIDUAL = 1.5
LOOP_PASSES = 2
SUBMAP_HALF = 4
ICP_ITERATIONS = 30
ICP_KEEP = 0.8
POINTS = 256  # points of a frame used (strided)


@dataclass(frozen=True)
class GraphReport:
    """What the loop closing did: loops kept (all passes), candidates tried, GNC inliers."""

    loops: int
    tried: int
    inliers: int


def strided(frame: np.ndarray) -> np.ndarray:
    """A frame's points thinned by a stride to about `POINTS` (the joins and the loops use these)."""
    return frame[:: max(1, len(frame) // POINTS)]


def trimmed_icp(src: np.ndarray, tree: cKDTree, guess: np.ndarray, iterations: int, keep: float) -> np.ndarray:
    """Point-to-point ICP of ``src`` (its own frame, any dimension) onto ``tree``'s points from
    ``guess``, each rigid fit on the ``keep`` share of closest matches; returns the pose."""
    pose = guess.copy()
    for _ in range(iterations):
        moved = g.apply(pose, src)
        dist, idx = tree.query(moved)
        kept = dist <= np.quantile(dist, keep)
        pose = g.homogeneous(*metrics.align_rigid(moved[kept], tree.data[idx[kept]])) @ pose
    return pose


def icp(src: np.ndarray, tree: cKDTree, guess: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """`trimmed_icp` of a planar frame ``src`` onto ``tree`` from ``guess``.

    Returns the pose, the mean residual of the kept matches and the fit's normal matrix in the
    tangent of a right perturbation, ``(x, y, theta)`` (``pose @ exp(xi)``).
    """
    pose = trimmed_icp(src, tree, guess, ICP_ITERATIONS, ICP_KEEP)
    dist, _ = tree.query(g.apply(pose, src))
    keep = dist <= np.quantile(dist, ICP_KEEP)
    p = src[keep]
    jac = np.zeros((len(p), 2, 3))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0
    jac[:, 0, 2], jac[:, 1, 2] = -p[:, 1], p[:, 0]
    normal = np.einsum("nki,nkj->ij", jac, jac)
    return pose, float(dist[keep].mean()), normal


def chain(wins: list[np.ndarray], ests: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """The chain's relative poses (each from the window where its pair is most central) and their
    per-axis spread ``(x, y, theta)`` where two windows overlap (1.4826 x the median absolute)."""
    best: dict[int, tuple[int, np.ndarray]] = {}
    pairs: dict[int, list[np.ndarray]] = {}
    for w, est in zip(wins, ests, strict=True):
        n = len(w)
        for a in range(n - 1):
            k = int(w[a])
            rel = g.relative(est[a], est[a + 1])
            pairs.setdefault(k, []).append(rel)
            centre = min(a, n - 2 - a)
            if k not in best or centre > best[k][0]:
                best[k] = (centre, rel)
    rels = [best[k][1] for k in range(len(best))]
    diffs = [g.se2_to_xytheta(g.relative(r[0], r[1])) for r in pairs.values() if len(r) == 2]
    # floored at a millionth of a step (windows that agree exactly would make the graph singular)
    step = float(np.median([np.linalg.norm(r[:2, 2]) for r in rels]))
    floor = np.array([1e-6 * step, 1e-6 * step, 1e-6])
    spread = 1.4826 * np.median(np.abs(diffs), axis=0) if diffs else floor
    return rels, np.maximum(spread, floor)


class _Loops:
    """Loop candidates verified by ICP against submaps, from a given estimate."""

    def __init__(self, frames: list[np.ndarray]) -> None:
        self.points = [strided(f) for f in frames]

    def submap(self, poses: np.ndarray, i: int) -> cKDTree:
        ks = range(max(0, i - SUBMAP_HALF), min(len(poses), i + SUBMAP_HALF + 1))
        return cKDTree(np.concatenate([g.apply(g.relative(poses[i], poses[k]), self.points[k]) for k in ks]))

    def chain_residual(self, poses: np.ndarray) -> float:
        """The median residual of a frame against the submap of frames before it."""
        lag = SUBMAP_HALF + 1
        res = [
            icp(self.points[k], self.submap(poses, k - lag), g.relative(poses[k - lag], poses[k]))[1]
            for k in range(lag, len(poses), 16)
        ]
        return float(np.median(res))

    def search(self, poses: np.ndarray, limit: float) -> tuple[list[Edge], int]:
        pos = poses[:, :2, 2]
        step = float(np.median(np.linalg.norm(np.diff(pos, axis=0), axis=1)))
        tree = cKDTree(pos)
        found: list[Edge] = []
        tried = 0
        for j in range(LOOP_GAP, len(poses), LOOP_EVERY):
            near = [i for i in tree.query_ball_point(pos[j], LOOP_RADIUS * step) if i <= j - LOOP_GAP]
            near.sort(key=lambda i: float(np.linalg.norm(pos[i] - pos[j])))
            chosen: list[int] = []
            for i in near:
                if len(chosen) == LOOP_PER_FRAME:
                    break
                if all(abs(i - c) >= LOOP_GAP // 2 for c in chosen):
                    chosen.append(i)
            for i in chosen:
                tried += 1
                pose, res, normal = icp(self.points[j], self.submap(poses, i), g.relative(poses[i], poses[j]))
                if res <= limit:
                    cov = np.linalg.inv(normal + 1e-9 * np.eye(3)) * res**2
                    found.append(Edge(i, j, pose, cov, loop=True))
        return found, tried


def close_loops(
    frames: list[np.ndarray], wins: list[np.ndarray], ests: list[np.ndarray], joined: np.ndarray
) -> tuple[np.ndarray, GraphReport]:
    """``joined`` (the windows' joined poses, ``(K, 3, 3)``) corrected by the pose graph of the
    windows' chain and the loops found on it (see the module docstring)."""
    rels, spread = chain(wins, ests)
    cov = np.diag((CHAIN_WIDEN * spread) ** 2)
    edges = [Edge(k, k + 1, rel, cov) for k, rel in enumerate(rels)]
    loops = _Loops(frames)
    limit = LOOP_RESIDUAL * loops.chain_residual(joined)
    found: dict[tuple[int, int], Edge] = {}
    poses, tried, inliers = joined, 0, 0
    for _ in range(LOOP_PASSES):
        new, n = loops.search(poses, limit)
        tried += n
        found.update({(e.i, e.j): e for e in new})
        if not found:
            break
        poses, inliers = optimise(poses, edges + list(found.values()))
    return poses, GraphReport(loops=len(found), tried=tried, inliers=inliers)
