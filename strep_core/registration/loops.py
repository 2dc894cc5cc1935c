"""Loop closures for the pose graph (`strep_core.registration.posegraph`): proposed by proximity
(`loop_candidates`) and verified by ICP (`proximity_loop_closures`), or on 2D keyframes proposed
and verified by the global scan matcher (`global_loop_closures`; docs/design/scan-matching.md)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.registration.clouds import from_se3
from strep_core.registration.pairwise import _icp_stages, icp_pair
from strep_core.registration.params import RegistrationParams
from strep_core.scanmatch import ScanMatcher


@dataclass
class LoopClosure:
    """A verified loop closure: ``transformation`` ``(4, 4)`` maps frame ``j`` into frame ``i``;
    ``score`` is the global matcher's (both ways), or the ICP fitness for a proximity loop."""

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
            res = _icp_stages(clouds[j], clouds[i], g.to_se3(match.pose), params, stages, ())
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


def loop_candidates(positions: np.ndarray, *, radius: float, min_gap: int, max_per_frame: int) -> list[tuple[int, int]]:
    """Loop-closure candidates by proximity: pairs ``(i, j)``, ``j - i >= min_gap``.

    For each frame j, the ``max_per_frame`` nearest earlier frames within ``radius`` (at least
    ``min_gap`` frames earlier), nearest first. Cost O(K log K) with a KD-tree, not O(K^2).

    Args:
        positions: ``(K, D)`` current frame positions (sequence unit).
        radius: search radius (sequence unit).
        min_gap: smallest index difference of a candidate pair.
        max_per_frame: cap per frame j.
    """
    from scipy.spatial import cKDTree

    if max_per_frame <= 0 or len(positions) <= min_gap:
        return []
    tree = cKDTree(positions)
    pairs: list[tuple[int, int]] = []
    for j, near in enumerate(tree.query_ball_point(positions, r=radius)):
        earlier = [i for i in near if i <= j - min_gap]
        if not earlier:
            continue
        dist = np.linalg.norm(positions[earlier] - positions[j], axis=1)
        pairs.extend((earlier[n], j) for n in np.argsort(dist, kind="stable")[:max_per_frame])
    return pairs


def proximity_loop_closures(
    clouds: list[Any],
    poses: np.ndarray,
    candidates: list[tuple[int, int]],
    params: RegistrationParams,
    *,
    scales: tuple[float, ...],
    min_fitness: float,
    on_frame: Callable[[int], None] | None = None,
) -> list[LoopClosure]:
    """The ``candidates`` (`loop_candidates`) that ICP verifies: from the current estimate's
    relative pose, stages ``scales``, no yaw search; kept at ``min_fitness``. In the order of
    frame j, then of the candidates; ``on_frame(j)`` after each frame j > 0."""
    poses3 = g.to_se3(np.asarray(poses, dtype=np.float64))
    by_frame: dict[int, list[int]] = {}
    for i, j in candidates:
        by_frame.setdefault(j, []).append(i)
    found: list[LoopClosure] = []
    for j in range(len(clouds)):
        for i in by_frame.get(j, []):
            guess = g.relative(poses3[i], poses3[j])
            res = icp_pair(clouds[j], clouds[i], guess, params, scales=scales, yaw_search=False)
            if res.fitness >= min_fitness:
                found.append(LoopClosure(i, j, res.transformation, res.fitness, res.fitness))
        if j > 0 and on_frame is not None:
            on_frame(j)
    return found
