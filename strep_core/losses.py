"""Losses of the learned methods: Chamfer over frame neighbourhoods and occupancy BCE.

All functions are pure: they take tensors (and index arrays) and return tensors; nothing is
stored between calls. Points are in *normalised* world coordinates (lengths divided by the
sequence's `scale`), so thresholds and loss magnitudes do not depend on pixels or metres.

Layout of a batch of frames: points of all frames concatenated into ``(M, D)`` with an
int64 array ``frame (M,)`` giving each point's frame number within the batch (``0..B-1``).
Frames may have different numbers of points (3D), so nothing here assumes equal sizes.

The learned loop's Chamfer term is `pair_chamfer`: matches laid out per frame pair ``(P, Q)``,
each query already moved into its target frame's axes (distances are the same in any frame).
Nearest neighbours are found by `strep_core.neighbours` on detached coordinates, and the matched
points gathered differentiably, so gradients reach both frames' poses. The flat-layout helpers
(`chamfer_matches`, `neighbourhood_chamfer`, `chamfer`) serve one-off comparisons and tests.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from strep_core.neighbours import nearest_in_frame
from strep_core.pairs import pair_queries

Robust = Literal["none", "truncated", "huber", "trimmed"]


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
    return mean(match_cost(d2, r2, plane=normals is not None, robust=robust, threshold=threshold))


def match_cost(d2: torch.Tensor, r2: torch.Tensor, *, plane: bool, robust: Robust, threshold: float) -> torch.Tensor:
    """Cost of each match from its squared distance ``d2`` and squared residual ``r2`` (any shape).

    Point to point (``plane=False``): `robust_squared` of ``d2``. Point to plane: `robust_squared`
    of ``r2``, except ``truncated``: ``min(r2, threshold^2)`` when the points are closer than
    ``threshold``, else ``threshold^2``. (``trimmed`` is a selection, see `pair_chamfer`.)
    """
    if not plane:
        return robust_squared(d2, robust=robust, threshold=threshold)
    if robust == "truncated":
        t2 = threshold * threshold
        return torch.where(d2 < t2, torch.clamp(r2, max=t2), torch.full_like(r2, t2))
    return robust_squared(r2, robust=robust, threshold=threshold)


def pair_chamfer(
    moved: torch.Tensor,
    matched: torch.Tensor,
    normals: torch.Tensor | None,
    valid: torch.Tensor,
    found: torch.Tensor,
    spatial: torch.Tensor,
    weight: torch.Tensor,
    *,
    robust: Robust,
    loop_robust: Robust,
    threshold: float,
    keep: float = 0.5,
) -> torch.Tensor:
    """Chamfer term of ``P`` ordered frame pairs, ``Q`` query slots each (differentiable in ``moved``).

    Args:
        moved: ``(P, Q, D)`` query points of each pair's query frame, in its target frame's axes.
        matched: ``(P, Q, D)`` their nearest target points; normals: ``(P, Q, D)`` the target
            points' unit normals (point to plane), or None (point to point).
        valid: ``(P, Q)`` bool, real query slots; found: ``(P, Q)`` bool, False where the search
            stopped at ``threshold`` (a truncated kernel: the match costs ``threshold^2``).
        spatial: ``(P,)`` bool, loop pairs (kernel ``loop_robust``; the others ``robust``).
        weight: ``(P,)`` weight of each pair's matches.
        robust, loop_robust, threshold: see `match_cost`. ``robust="trimmed"``: only the ``keep``
            fraction (at least one) of each pair's matches with the smallest distances count, as a
            weighted mean of their ``r2``.

    Returns:
        Scalar: ``sum_(p,q) w_p rho(p, q) / #valid`` (a weighted mean of the match costs), the
        trimmed temporal part being its own weighted mean scaled by its share of the matches.
    """
    diff = moved - matched
    d2 = diff.square().sum(-1)
    r2 = d2 if normals is None else (diff * normals).sum(-1).square()
    plane = normals is not None
    t2 = threshold * threshold
    n = valid.sum().clamp_min(1)
    w = weight[:, None] * valid
    near = ~spatial[:, None]

    def part(kernel: Robust, rows: torch.Tensor) -> torch.Tensor:
        if kernel == "trimmed":  # a weighted mean of the kept r2, scaled by the rows' share
            kept = w * rows * trimmed_rows(d2.detach(), valid, keep)
            return (r2 * kept).sum() / kept.sum().clamp_min(1e-12) * ((valid & rows).sum() / n)
        c = match_cost(d2, r2, plane=plane, robust=kernel, threshold=threshold)
        c = torch.where(found, c, torch.full_like(c, t2))
        return (c * w * rows).sum() / n

    if robust == loop_robust and robust != "trimmed":
        return part(robust, torch.ones_like(near))
    return part(robust, near) + part(loop_robust, ~near)


def trimmed_rows(d2: torch.Tensor, valid: torch.Tensor, keep: float) -> torch.Tensor:
    """``(P, Q)`` bool: the ``keep`` fraction (at least one) of each row's valid ``d2``, smallest first."""
    order = torch.sort(d2.masked_fill(~valid, float("inf")), dim=-1, stable=True).indices
    rank = torch.empty_like(order).scatter_(-1, order, torch.arange(d2.shape[-1], device=d2.device).expand_as(order))
    limit = torch.ceil(keep * valid.sum(-1, keepdim=True)).clamp_min(1)
    return (rank < limit) & valid


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
    u = torch.rand((r, per_ray, 1), generator=generator, dtype=hits.dtype, device=generator.device).to(hits.device)
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
