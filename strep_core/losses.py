"""Losses of the learned methods: Chamfer over frame neighbourhoods and occupancy BCE.

All functions are pure: they take tensors (and index arrays) and return tensors; nothing is
stored between calls. Points are in *normalised* world coordinates (lengths divided by the
sequence's `scale`), so thresholds and loss magnitudes do not depend on pixels or metres.

Layout of a batch of frames: points of all frames concatenated into ``(M, D)`` with an
int64 array ``frame (M,)`` giving each point's frame number within the batch (``0..B-1``).
Frames may have different numbers of points (3D), so nothing here assumes equal sizes.

Nearest neighbours are searched on detached coordinates with one `scipy.spatial.cKDTree`
over the whole batch, *lifted* by the frame number: a point ``p`` of frame ``j`` is stored as
``(p, C j)`` with ``C`` larger than the batch's extent, so a query ``(q, C j)`` can only
find points of frame ``j``. One tree build and one query call (``workers=-1``) serve every
frame pair of the neighbourhood, with no Python loop over frames and no ``N^2`` memory.
The matched points are then gathered from the differentiable tensor, so gradients reach
both frames' poses. Cost: ``O(M log M)`` for the tree, ``O(Q log M)`` for ``Q`` queries.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

Robust = Literal["none", "truncated", "huber", "trimmed"]


# --------------------------------------------------------------------------------------------
# Nearest neighbours


def _lift(points: np.ndarray, frame: np.ndarray, c: float) -> np.ndarray:
    return np.concatenate([points, (c * frame.astype(np.float64))[:, None]], 1)


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
        from scipy.spatial import cKDTree

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


def pair_queries(
    frame: np.ndarray, pairs: np.ndarray, query: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Every (query point, target frame) for ordered frame ``pairs``.

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


# --------------------------------------------------------------------------------------------
# Chamfer


def robust_squared(d2: torch.Tensor, *, robust: Robust, threshold: float) -> torch.Tensor:
    """Per-match cost of squared distances ``d2 (Q,)``.

    * ``"none"``: ``d2`` (the paper's squared Chamfer).
    * ``"truncated"``: ``min(d2, threshold^2)``: matches farther than ``threshold`` (no
      overlap) cost a constant and pull nothing.
    * ``"huber"``: ``d2`` below ``threshold``, ``2 threshold |d| - threshold^2`` above
      (Huber on the distance, scaled by 2 so it equals ``d2`` inside).
    """
    if robust == "none":
        return d2
    t2 = threshold * threshold
    if robust == "truncated":
        return torch.clamp(d2, max=t2)
    if robust == "huber":
        d = torch.sqrt(d2.clamp_min(1e-30))
        return torch.where(d2 <= t2, d2, 2.0 * threshold * d - t2)
    raise ValueError(f"unknown robust form {robust!r}")


def chamfer_matches(
    points: torch.Tensor,
    src: np.ndarray,
    idx: np.ndarray,
    *,
    robust: Robust = "none",
    threshold: float = 1.0,
    normals: torch.Tensor | None = None,
    weights: np.ndarray | None = None,
    groups: np.ndarray | None = None,
    keep: float = 0.5,
) -> torch.Tensor:
    """Mean robust squared distance between matched points (differentiable in ``points``).

    Args:
        points: ``(M, D)`` world points (normalised units), requires grad as needed.
        src: ``(Q,)`` query indices; idx: ``(Q,)`` their matched neighbours' indices.
        robust, threshold: see `robust_squared`.
        normals: optional ``(M, D)`` unit normals of the points in world axes. Given, the
            distance of a match is measured along the matched point's normal
            (point-to-plane: ``r^2 = ((a - b) . n_b)^2``); with ``robust="truncated"`` a match
            costs ``min(r^2, threshold^2)`` when its points are closer than ``threshold``, and
            ``threshold^2`` otherwise.

        groups, keep: with ``robust="trimmed"``, the group (frame pair) of each match; only the
            ``keep`` fraction of each group's matches with the smallest distances count
            (trimmed Chamfer: the part of a partial overlap that matches nothing has no pull).

    Returns:
        Scalar: ``mean_q rho(|points[src_q] - points[idx_q]|^2)`` (point to point).
    """
    if len(src) == 0:
        return points.sum() * 0.0
    s = torch.as_tensor(src, device=points.device)
    t = torch.as_tensor(idx, device=points.device)
    diff = points.index_select(0, s) - points.index_select(0, t)
    d2 = (diff * diff).sum(-1)
    wt = None if weights is None else torch.as_tensor(weights, dtype=points.dtype, device=points.device)

    def mean(x: torch.Tensor) -> torch.Tensor:
        return x.mean() if wt is None else (x * wt).mean()

    r2 = d2 if normals is None else (diff * normals.index_select(0, t)).sum(-1) ** 2
    if robust == "trimmed":
        kept = torch.as_tensor(trimmed_mask(d2.detach().cpu().numpy(), groups, keep), device=points.device)
        w = kept.to(points.dtype) if wt is None else kept.to(points.dtype) * wt
        return (r2 * w).sum() / w.sum().clamp_min(1e-12)
    if normals is None:
        return mean(robust_squared(d2, robust=robust, threshold=threshold))
    if robust == "truncated":
        t2 = threshold * threshold
        return mean(torch.where(d2 < t2, torch.clamp(r2, max=t2), torch.full_like(r2, t2)))
    return mean(robust_squared(r2, robust=robust, threshold=threshold))


def trimmed_mask(d2: np.ndarray, groups: np.ndarray | None, keep: float) -> np.ndarray:
    """``(Q,)`` bool: the ``keep`` fraction (at least one) of each group's matches with the smallest ``d2``."""
    groups = np.zeros(len(d2), np.int64) if groups is None else np.asarray(groups)
    _, gid, counts = np.unique(groups, return_inverse=True, return_counts=True)
    order = np.lexsort((d2, gid))
    first = np.r_[0, np.cumsum(counts)[:-1]]
    rank = np.empty(len(d2), np.int64)
    rank[order] = np.arange(len(d2)) - first[gid[order]]
    return rank < np.maximum(1, np.ceil(keep * counts[gid]))


def weak_directions(normals: np.ndarray) -> np.ndarray:
    """``(D, D)`` penalty matrix of a frame's unit ``normals (N, D)``, in its own axes.

    ``I - C / lambda_max(C)`` with ``C`` the normals' mean outer product: zero along the direction
    they constrain most, near one along a direction none of them faces (a corridor's axis).
    A frame without normals gets the identity (nothing constrains it).
    """
    d = normals.shape[1]
    c = normals.T @ normals / max(len(normals), 1)
    top = float(np.linalg.eigvalsh(c)[-1])
    return np.eye(d) if top <= 1e-12 else np.eye(d) - c / top


def frame_normals(points: np.ndarray, *, k: int | None = None) -> np.ndarray:
    """Unit normals ``(N, D)`` of a frame's points ``(N, D)`` by PCA of ``k`` nearest neighbours.

    The normal is the direction of least variance of each point's neighbourhood (``k``
    defaults to 6 in 2D and 10 in 3D); its sign is arbitrary (point-to-plane residuals are
    squared). Frames with fewer than ``D + 1`` points get zero normals.
    """
    n, d = points.shape
    k = min(k or (6 if d == 2 else 10), n)
    if n <= d:
        return np.zeros_like(points)
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return vecs[:, :, 0]


def neighbourhood_chamfer(
    points: torch.Tensor,
    frame: np.ndarray,
    pairs: np.ndarray,
    *,
    query: np.ndarray | None = None,
    robust: Robust = "none",
    threshold: float = 1.0,
) -> torch.Tensor:
    """Chamfer loss of every frame against its neighbours (the ordered ``pairs``).

    ``L = mean over (i, j) in pairs, a in S_i, of rho(min_{b in S_j} |a - b|^2)``, i.e. the
    paper's ``sum_i sum_{j in N(i)} d_Chamfer(S_i, S_j)`` (both directions, since ``pairs``
    holds both orders) up to a constant normalisation (a mean instead of a sum, so the
    magnitude does not grow with the number of points) and the robust ``rho`` of
    `robust_squared`.

    Args:
        points: ``(M, D)`` world points of the batch (normalised units).
        frame: ``(M,)`` int frame number of each point within the batch (contiguous, sorted).
        pairs: ``(P, 2)`` ordered frame pairs, e.g. from `frame_pairs`.
        query: optional ``(Q0,)`` subset of points that query (targets are always all points).
        robust, threshold: see `robust_squared` (threshold in normalised units).

    Returns:
        Scalar tensor.
    """
    src, target = pair_queries(frame, pairs, query)
    idx, _ = nearest_in_frame(points.detach().cpu().numpy(), frame, src, target)
    return chamfer_matches(points, src, idx, robust=robust, threshold=threshold)


def chamfer(a: torch.Tensor, b: torch.Tensor, *, robust: Robust = "none", threshold: float = 1.0) -> torch.Tensor:
    """Symmetric Chamfer distance of two point sets ``a (Na, D)`` and ``b (Nb, D)``.

    ``sum_a rho(min_b |a-b|^2) + sum_b rho(min_a |a-b|^2)`` (sums, as in the paper's
    definition), with nearest neighbours by KD-tree and a differentiable gather.
    """
    pts = torch.cat([a, b], 0)
    frame = np.repeat(np.array([0, 1]), [len(a), len(b)])
    src, target = pair_queries(frame, np.array([[0, 1], [1, 0]]))
    idx, _ = nearest_in_frame(pts.detach().cpu().numpy(), frame, src, target)
    return chamfer_matches(pts, src, idx, robust=robust, threshold=threshold) * len(src)


# --------------------------------------------------------------------------------------------
# Occupancy


def free_space_samples(
    origins: torch.Tensor, hits: torch.Tensor, generator: torch.Generator, *, per_ray: int = 1
) -> torch.Tensor:
    """Points drawn uniformly on the segments from sensor origins to hits.

    Args:
        origins: ``(R, D)`` start of each ray (the sensor origin, world coordinates).
        hits: ``(R, D)`` end of each ray (an observed point, world coordinates).
        generator: torch random generator (seeded by the caller).
        per_ray: samples per ray.

    Returns:
        ``(R * per_ray, D)``: ``o + u (h - o)`` with ``u ~ U[0, 1)``, ray-major order
        (the samples of ray ``r`` are rows ``r*per_ray ... r*per_ray+per_ray-1``).
        Differentiable in ``origins`` and ``hits``.
    """
    r = len(hits)
    u = torch.rand((r, per_ray, 1), generator=generator, dtype=hits.dtype, device="cpu").to(hits.device)
    out = origins[:, None, :] + u * (hits - origins)[:, None, :]
    return out.reshape(r * per_ray, hits.shape[-1])


def occupancy_bce(logits_occupied: torch.Tensor, logits_free: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy: observed points labelled 1, free-space samples labelled 0.

    ``L = mean BCE(occupied, 1) + mean BCE(free, 0)`` (the paper's ``BE[F, 1] + BE[S(F), 0]``
    with means instead of sums).

    Args:
        logits_occupied: ``(P,)`` occupancy logits at observed points.
        logits_free: ``(Q,)`` logits at free-space samples.
    """
    occ = F.binary_cross_entropy_with_logits(logits_occupied, torch.ones_like(logits_occupied))
    if logits_free.numel() == 0:
        return occ
    free = F.binary_cross_entropy_with_logits(logits_free, torch.zeros_like(logits_free))
    return occ + free
