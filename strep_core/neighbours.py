"""Nearest neighbours of query points, each searched in one target frame.

The learned loop asks for the nearest point of frame ``j`` to points of frame ``i`` that it has
moved into ``j``'s own axes (`strep_core.plan`): the searched points are then the frames' *local*
points, which never change, so nothing is rebuilt per iteration. `FrameIndex` holds them and
answers in one of two ways, chosen in one place (`FrameIndex.__init__`, measured in
docs/design/optimiser.md):

* on a GPU, chunked brute force per frame pair: ``(P, Q, N)`` squared distances and an argmin,
  no host copy and no sync;
* on the CPU, one `scipy.spatial.cKDTree` per frame, built once: queries only, grouped by target
  frame, the groups shared among the run's threads. Rows whose matches count only within a
  distance (a truncated kernel) search within it and stop early. (One tree over every frame's
  points lifted by the frame number, as `nearest_in_frame` builds, measured 1.5-2x slower.)

`nearest_in_frame` searches arbitrary (world) points, lifted: a point ``p`` of frame ``j`` is
stored as ``(p, C j)`` with ``C`` beyond any in-frame distance, so ``(q, C j)`` finds frame ``j``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Literal

import numpy as np
import torch
from scipy.spatial import cKDTree

Backend = Literal["auto", "tree", "brute"]

# Elements of one brute-force distance block (P_chunk x Q x N x D): 64 M floats, 256 MB.
_BRUTE_BLOCK = 1 << 26
# Padding coordinate of frames with fewer points than the widest: never nearest to a real query.
PAD = 1.0e6


def _lift(points: np.ndarray, frame: np.ndarray, c: float) -> np.ndarray:
    return np.concatenate([points, (c * frame.astype(np.float64))[:, None]], 1)


def nearest_in_frame(
    points: np.ndarray, frame: np.ndarray, src: np.ndarray, target_frame: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of frame ``target_frame[q]`` to point ``src[q]``, for every query ``q``.

    Args:
        points: ``(M, D)`` float coordinates (detached, any unit).
        frame: ``(M,)`` int frame number of each point.
        src: ``(Q,)`` indices into ``points`` of the query points.
        target_frame: ``(Q,)`` frame each query searches.

    Returns:
        ``idx (Q,)`` indices into ``points`` of the nearest neighbours and ``dist (Q,)`` their
        Euclidean distances.
    """
    points = np.asarray(points, dtype=np.float64)
    extent = float(np.linalg.norm(np.ptp(points, axis=0))) if len(points) else 0.0
    c = 2.0 * extent + 1.0  # any in-frame distance is <= extent < c; a cross-frame one >= c
    tree = cKDTree(_lift(points, frame, c), balanced_tree=False, compact_nodes=False)
    dist, idx = tree.query(_lift(points[src], target_frame, c), k=1, workers=-1)
    return idx.astype(np.int64), dist


def brute_nearest(queries: torch.Tensor, targets: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """``(P, Q)`` slots of the nearest point of ``targets[frames[p]]`` to each ``queries[p, q]``.

    Args:
        queries: ``(P, Q, D)`` detached query points, in their target frame's axes.
        targets: ``(K, N, D)`` every frame's points, padded with `PAD`.
        frames: ``(P,)`` int64 target frame of each row.
    """
    p, q, d = queries.shape
    rows = max(1, _BRUTE_BLOCK // max(1, q * targets.shape[1] * d))
    out = []
    for s in range(0, p, rows):
        t = targets.index_select(0, frames[s : s + rows])
        out.append((queries[s : s + rows, :, None, :] - t[:, None, :, :]).square().sum(-1).argmin(-1))
    return torch.cat(out) if out else torch.zeros((0, q), dtype=torch.int64, device=queries.device)


class FrameIndex:
    """Every frame's static local points, searchable frame by frame (see the module docstring).

    Args:
        points: ``(K, N, D)`` local points, frame ``k``'s first ``counts[k]`` rows real, the rest
            `PAD`.
        counts: ``(K,)`` int64 points per frame.
        backend: ``auto`` (the KD-trees on a CPU, brute force on a GPU), ``tree`` or ``brute``.
    """

    def __init__(self, points: torch.Tensor, counts: torch.Tensor, *, backend: Backend = "auto") -> None:
        self.points = points
        if backend == "auto":
            backend = "tree" if points.device.type == "cpu" else "brute"
        self.backend = backend
        self._trees: list[cKDTree] = []
        if backend == "tree":
            n = counts.cpu().numpy()
            host = points.detach().cpu().double().numpy()
            self._trees = [cKDTree(host[k, : max(n[k], 1)]) for k in range(len(n))]

    def nearest(
        self, queries: torch.Tensor, frames: torch.Tensor, *, within: torch.Tensor | None = None, limit: float = 0.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Nearest point of frame ``frames[p]`` to every ``queries[p, q]``.

        Args:
            queries: ``(P, Q, D)`` query points in their target frame's axes (detached).
            frames: ``(P,)`` int64 target frame of each row.
            within: optional ``(P,)`` bool rows whose matches count only closer than ``limit``
                (the KD-tree stops searching there; brute force finds them all anyway).

        Returns:
            ``slot (P, Q)`` int64 index of the match within its frame's points, and
            ``found (P, Q)`` bool (False only for a ``within`` row's query with nothing closer
            than ``limit``; its slot is then 0).
        """
        if not self._trees:
            slot = brute_nearest(queries, self.points, frames)
            return slot, torch.ones_like(slot, dtype=torch.bool)
        p, q, d = queries.shape
        qs = queries.detach().double().numpy()
        near = np.zeros(p, bool) if within is None else within.numpy()
        # rows grouped by (target frame, bounded or not): one query call per group
        key = frames.numpy() * 2 + near
        order = np.argsort(key, kind="stable")
        cuts = np.flatnonzero(np.diff(key[order])) + 1
        slot = np.zeros((p, q), np.int64)
        found = np.ones((p, q), bool)

        def search(rows: np.ndarray) -> None:
            tree, bounded = self._trees[key[rows[0]] // 2], bool(near[rows[0]])
            dist, i = tree.query(qs[rows].reshape(-1, d), k=1, distance_upper_bound=limit if bounded else np.inf)
            ok = np.isfinite(dist)
            slot[rows] = np.where(ok, i, 0).reshape(len(rows), q)
            found[rows] = ok.reshape(len(rows), q)

        groups = np.split(order, cuts) if p else []
        workers = min(torch.get_num_threads(), len(groups))  # the run's threads (``config.threads``)
        if workers > 1:  # cKDTree.query releases the GIL
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(search, groups))
        else:
            for rows in groups:
                search(rows)
        return torch.from_numpy(slot), torch.from_numpy(found)
