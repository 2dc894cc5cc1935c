"""Which frames look into which: temporal and spatial frame pairs, and a batch's partners.

Pairs are ordered ``(i, j)``: points of frame ``i`` search frame ``j``. Temporal pairs lie within
``+-window`` frames; spatial (loop) pairs are frames farther apart in time whose sensors are near
each other at the current poses. Everything here is small host-side index work, done once per
batch and pair refresh (`strep_core.plan`), never per iteration.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def frame_pairs(
    num_frames: int,
    window: int,
    *,
    positions: np.ndarray | None = None,
    radius: float | None = None,
    max_per_frame: int = 8,
) -> np.ndarray:
    """Ordered pairs ``(i, j)`` of neighbouring frames, both orders of every pair.

    Temporal neighbours: ``0 < |i - j| <= window``. With ``positions`` and ``radius``, also
    spatial neighbours: frames farther apart in time whose sensor positions are closer than
    ``radius`` (at most ``max_per_frame`` nearest per frame), i.e. revisits of a place.

    Args:
        num_frames: ``B``.
        window: temporal half-width (>= 0).
        positions: optional ``(B, D)`` sensor positions in the world (current estimate).
        radius: spatial neighbour distance, same unit as ``positions``.

    Returns:
        ``(P, 2)`` int64, sorted and without duplicates.
    """
    i = np.arange(num_frames)
    parts = []
    for d in range(1, min(window, num_frames - 1) + 1):
        parts.append(np.stack([i[:-d], i[d:]], 1))
    if positions is not None and radius and num_frames > window + 1:
        k = min(max_per_frame + 2 * window + 1, num_frames)
        dist, nn = cKDTree(positions).query(positions, k=k)
        a = np.repeat(i, k)
        b, dd = nn.ravel(), dist.ravel()
        keep = (dd < radius) & (np.abs(a - b) > window) & (b < num_frames)
        a, b = a[keep], b[keep]
        # at most max_per_frame per frame, nearest first (query order is by distance)
        rank = np.zeros_like(a)
        if len(a):
            first = np.r_[0, np.flatnonzero(np.diff(a)) + 1]
            rank = np.arange(len(a)) - np.repeat(first, np.diff(np.r_[first, len(a)]))
        keep = rank < max_per_frame
        parts.append(np.stack([np.minimum(a, b), np.maximum(a, b)], 1)[keep])
    if not parts:
        return np.zeros((0, 2), dtype=np.int64)
    und = np.unique(np.concatenate(parts).astype(np.int64), axis=0)
    return np.concatenate([und, und[:, ::-1]]).astype(np.int64)


def temporal_pairs(frames: np.ndarray, window: int) -> np.ndarray:
    """Ordered pairs of positions ``(a, b)`` in ``frames`` with ``0 < |frames[a] - frames[b]| <= window``."""
    a, b = np.nonzero(np.abs(frames[:, None] - frames[None, :]) <= window)
    keep = a != b
    return np.stack([a[keep], b[keep]], 1).astype(np.int64)


def with_partners(frames: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``frames`` plus their spatial partners in ``pairs`` (sorted, unique), and a mask of the
    partners that are not in ``frames`` themselves (the step holds their poses fixed)."""
    if len(pairs) == 0:
        return frames, np.zeros(len(frames), dtype=bool)
    inside = np.isin(pairs[:, 0], frames)
    union = np.union1d(frames, pairs[inside, 1])
    return union, ~np.isin(union, frames)


def local_pairs(pairs: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Pairs with both frames in ``frames`` (sorted), renumbered to positions within ``frames``."""
    if len(pairs) == 0:
        return pairs
    ok = np.isin(pairs[:, 0], frames) & np.isin(pairs[:, 1], frames)
    return np.searchsorted(frames, pairs[ok])


def pair_queries(
    frame: np.ndarray, pairs: np.ndarray, query: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Every (query point, target frame) for ordered frame ``pairs``, in a flat layout.

    Args:
        frame: ``(M,)`` int frame number of each point; points of a frame are contiguous
            and frames appear in increasing order.
        pairs: ``(P, 2)`` ordered pairs ``(i, j)``: points of ``i`` look into frame ``j``.
        query: optional ``(Q0,)`` indices of the points that query (default: all),
            sorted by frame.

    Returns:
        ``src (Q,)`` indices of query points and ``target_frame (Q,)``.
    """
    src0 = np.arange(len(frame)) if query is None else np.asarray(query, dtype=np.int64)
    if len(pairs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    nf = int(frame.max()) + 1
    counts = np.bincount(frame[src0], minlength=nf)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    n = counts[pairs[:, 0]]
    total = int(n.sum())
    # ragged arange: for pair p, positions starts[i_p] ... starts[i_p] + n_p - 1 in src0
    offs = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
    pos = np.repeat(starts[pairs[:, 0]], n) + offs
    return src0[pos], np.repeat(pairs[:, 1], n)
