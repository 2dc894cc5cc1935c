"""A step's plan: which frames it moves and which frame pairs its Chamfer term compares.

A `BatchPlan` is built on the host once per batch and pair refresh (every ``optim.pair_interval``
iterations once loop pairs are on), then lives on the run's device: the iterations between two
refreshes read nothing back from it. `sample_slots` draws each step's query points on the device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from strep_core.pairs import local_pairs, temporal_pairs, with_partners


@dataclass(frozen=True)
class BatchPlan:
    """One batch's frames and ordered frame pairs, as tensors on the run's device.

    Attributes:
        frames: ``(B,)`` sequence index of every frame of the step: the batch and its spatial
            partners outside it (held at their latest poses).
        moving: ``(Bm,)`` positions within ``frames`` of the frames the step moves (the batch).
        moving_frames: ``(Bm,)`` their sequence indices.
        has_fixed: whether any partner is held fixed (else ``moving`` is every position).
        upto: latents are computed for frames ``0 .. upto-1`` (the chain starts at frame 0).
        src, dst: ``(P,)`` positions within ``frames`` of each pair's query and target frame.
        spatial: ``(P,)`` bool, pairs farther apart in time than the window (loop pairs).
        weight: ``(P,)`` float weight of each pair's matches (``min(1, window / span)`` under
            ``loop_weight="span"``, else 1).
    """

    frames: torch.Tensor
    moving: torch.Tensor
    moving_frames: torch.Tensor
    has_fixed: bool
    upto: int
    src: torch.Tensor
    dst: torch.Tensor
    spatial: torch.Tensor
    weight: torch.Tensor

    @property
    def dst_frames(self) -> torch.Tensor:
        return self.frames.index_select(0, self.dst)


def build_plan(
    batch: np.ndarray, pairs_all: np.ndarray, *, window: int, span_weight: bool, device: torch.device
) -> BatchPlan:
    """The plan of a step on ``batch`` (sorted sequence indices) given every spatial pair ``(P0, 2)``.

    Pairs: every temporal pair within ``window`` and every spatial pair among the step's frames,
    both orders, without those joining two fixed partners (they would move nothing).
    """
    frames, fixed = with_partners(batch, pairs_all)
    pairs = np.unique(np.concatenate([temporal_pairs(frames, window), local_pairs(pairs_all, frames)]), axis=0)
    if fixed.any():
        pairs = pairs[~(fixed[pairs[:, 0]] & fixed[pairs[:, 1]])]
    span = np.abs(frames[pairs[:, 0]] - frames[pairs[:, 1]])
    weight = np.minimum(1.0, window / np.maximum(span, 1)) if span_weight else np.ones(len(pairs))
    moving = np.flatnonzero(~fixed)

    ints = [frames, moving, frames[moving], pairs[:, 0], pairs[:, 1], (span > window).astype(np.int64)]
    parts = torch.split(_upload(np.concatenate(ints).astype(np.int64), device), [len(x) for x in ints])
    return BatchPlan(
        frames=parts[0],
        moving=parts[1],
        moving_frames=parts[2],
        has_fixed=bool(fixed.any()),
        upto=int(frames[moving[-1]]) + 1,
        src=parts[3],
        dst=parts[4],
        spatial=parts[5].bool(),
        weight=_upload(weight.astype(np.float32), device),
    )


def _upload(values: np.ndarray, device: torch.device) -> torch.Tensor:
    """``values`` on ``device``: on a GPU from pinned memory without blocking the host (the plan's
    indices travel as one packed copy, its weights as another: 2 copies a refresh, not 8)."""
    host = torch.from_numpy(values)
    if device.type != "cuda":
        return host.to(device)
    return host.pin_memory().to(device, non_blocking=True)


def sample_slots(
    counts: torch.Tensor, k: int | None, width: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """A stratified random sample of ``k`` points of every frame (all of a frame with ``<= k``).

    Frame ``f`` with ``n`` points gets ``floor((j + u_j) n / m)``, ``j < m = min(n, k)``,
    ``u_j ~ U[0, 1)``: distinct points spread evenly over the frame's storage order (over the
    scan angle for laser scans).

    Args:
        counts: ``(B,)`` int64 points of each frame (on the device).
        k: samples per frame; ``None``: every point.
        width: the padded frame width ``N``.
        generator: the run's generator on the device.

    Returns:
        ``slot (B, k')`` int64 point indices within each frame and ``valid (B, k')`` bool,
        ``k' = min(k, width)``.
    """
    k = width if k is None else min(k, width)
    j = torch.arange(k, device=counts.device)
    m = counts.clamp(max=k)[:, None]
    u = torch.rand((len(counts), k), generator=generator, device=counts.device)
    slot = torch.floor((j + u) * (counts[:, None] / m.clamp_min(1))).long()
    return torch.minimum(slot, (counts[:, None] - 1).clamp_min(0)), j < m
