"""The sequence packed for the optimiser of the learned methods, and the batches drawn from it.

Everything here is data handling around `strep_core.optimize`'s loop: normalising and packing
the frames once per run (`prepare`), choosing each step's frames (`batch_schedule`, spatial
partners) and its query points (`sample_per_frame`), and the pair lists the Chamfer term uses.
Lengths are normalised by `Sequence.scale` (docs/design/warm-start.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from strep_core import losses
from strep_core.config import RunConfig
from strep_core.sequence import Sequence


@dataclass
class Prepared:
    """A sequence as float32 tensors in normalised units.

    Attributes:
        dim: D.
        scale: the sequence's `scale` (length unit per normalised unit).
        points: ``(M, D)`` local points of every frame (working set), concatenated.
        starts: ``(K + 1,)`` int64: frame ``k`` owns ``points[starts[k]:starts[k+1]]``.
        decoder_points: ``(K, Nd, D)`` the fixed decoder input of every frame.
        origins: ``(K, D)`` sensor origins, local.
        init: ``(K, D+1, D+1)`` warm-start poses, translations normalised.
        centre: ``(D,)`` normalised world centre of the warm-start trajectory (occupancy input
            is ``world - centre``).
        normals: ``(M, D)`` local unit normals of ``points`` (``loss.chamfer="plane"``), else None.
    """

    dim: int
    scale: float
    points: torch.Tensor
    starts: np.ndarray
    decoder_points: torch.Tensor
    origins: torch.Tensor
    init: torch.Tensor
    centre: torch.Tensor
    normals: torch.Tensor | None = None

    @property
    def num_frames(self) -> int:
        return len(self.starts) - 1


def _strided(n: int, m: int | None) -> np.ndarray:
    """``min(n, m)`` evenly spread indices of ``range(n)``; ``m`` of them (repeating) if n < m."""
    if m is None or n == m:
        return np.arange(n)
    return np.floor(np.arange(m) * (n / m)).astype(np.int64)


def prepare(
    seq: Sequence, init_poses: np.ndarray, config: RunConfig, device: torch.device, rng: np.random.Generator
) -> Prepared:
    """Normalise and pack a sequence for the optimiser (see `Prepared`)."""
    scale = seq.scale()
    cap = config.optim.max_points_per_frame
    frames = []
    for f in seq.frames:
        if len(f) > cap:
            f = f[np.sort(rng.choice(len(f), cap, replace=False))]
        frames.append(f / scale)
    counts = np.array([len(f) for f in frames])
    nd = config.model.decoder_points
    nd = int(counts.max()) if nd is None else min(nd, int(counts.max()))
    dec = np.stack([f[_strided(len(f), nd)] for f in frames])
    init = np.array(init_poses, dtype=np.float64, copy=True)
    d = seq.dim
    init[:, :d, d] /= scale
    assert seq.origins is not None

    def f32(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=device)

    return Prepared(
        dim=d,
        scale=scale,
        points=f32(np.concatenate(frames)),
        starts=np.r_[0, np.cumsum(counts)].astype(np.int64),
        decoder_points=f32(dec),
        origins=f32(seq.origins / scale),
        init=f32(init),
        centre=f32(init[:, :d, d].mean(0)),
        normals=(
            f32(np.concatenate([losses.frame_normals(f) for f in frames])) if config.loss.chamfer == "plane" else None
        ),
    )


def ragged_indices(starts: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point indices of ``frames`` (in order) and each one's position within ``frames``."""
    n = starts[frames + 1] - starts[frames]
    offs = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    return np.repeat(starts[frames], n) + offs, np.repeat(np.arange(len(frames)), n)


def sample_per_frame(starts: np.ndarray, frames: np.ndarray, k: int | None, rng: np.random.Generator) -> np.ndarray:
    """Stratified random sample of ``k`` points of every frame (all if it has ``<= k``).

    Frame ``f`` with ``n`` points gets ``floor((j + u_j) n / k)``, ``j < k``, ``u_j ~ U[0, 1)``:
    distinct points spread evenly over the frame's storage order (over the scan angle for
    laser scans), in ``O(k)`` per frame.

    Returns:
        Sorted indices into the batch's concatenated points (frames in the order given).
    """
    n = starts[frames + 1] - starts[frames]
    first = np.r_[0, np.cumsum(n)[:-1]]
    if k is None or k >= n.max():
        return np.arange(int(n.sum()))
    m = np.minimum(n, k)
    j = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
    nn, mm = np.repeat(n, m), np.repeat(m, m)
    pos = np.floor((j + rng.random(len(j))) * (nn / mm)).astype(np.int64)
    return np.repeat(first, m) + np.minimum(pos, nn - 1)


# --------------------------------------------------------------------------------------------
# Batches


# Frames per step of a long sequence under ``optim.batch_frames="auto"``: every benchmark window and
# sample (up to 256 frames, v1_pose0) keeps one batch of all frames; whole logs get bounded
# batches, so the refinement's peak memory stays flat in the log's length (docs/design/whole-logs.md).
AUTO_BATCH_FRAMES = 256


def batch_size(num_frames: int, batch_frames: int | str | None) -> int | None:
    """Frames per batch of a ``num_frames`` sequence: ``None`` for one batch of all frames.

    ``"auto"``: all frames up to `AUTO_BATCH_FRAMES`, else batches of that many.
    """
    if batch_frames == "auto":
        return None if num_frames <= AUTO_BATCH_FRAMES else AUTO_BATCH_FRAMES
    assert batch_frames is None or isinstance(batch_frames, int)
    return None if batch_frames is None or batch_frames >= num_frames else batch_frames


def total_steps(num_frames: int, config: RunConfig) -> int:
    """Optimiser steps of a run: ``optim.iterations`` per batch, so every frame gets as many
    updates however the sequence is cut (each step takes the next batch in turn)."""
    batches = batch_schedule(num_frames, batch_size(num_frames, config.optim.batch_frames), config.loss.window)
    return config.optim.iterations * len(batches)


def batch_schedule(num_frames: int, batch: int | None, window: int) -> list[np.ndarray]:
    """Contiguous batches of frames covering the sequence, overlapping by ``window`` frames.

    Consecutive batches share ``window`` frames so every temporal neighbour pair lies
    inside at least one batch. ``None`` or ``batch >= num_frames``: one batch of all frames.
    """
    if batch is None or batch >= num_frames:
        return [np.arange(num_frames)]
    stride = max(1, batch - window)
    starts = [*list(range(0, num_frames - batch, stride)), num_frames - batch]
    return [np.arange(s, s + batch) for s in starts]


def with_partners(frames: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``frames`` plus their spatial partners in ``pairs`` (sorted, unique), and a mask of the
    partners that are not in ``frames`` themselves (the step holds their poses fixed)."""
    if len(pairs) == 0:
        return frames, np.zeros(len(frames), dtype=bool)
    inside = np.isin(pairs[:, 0], frames)
    union = np.union1d(frames, pairs[inside, 1])
    return union, ~np.isin(union, frames)


def local_pairs(pairs: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Pairs with both frames in ``frames``, renumbered to positions within ``frames``."""
    if len(pairs) == 0:
        return pairs
    ok = np.isin(pairs[:, 0], frames) & np.isin(pairs[:, 1], frames)
    return np.searchsorted(frames, pairs[ok])


def weak_matrices(prep: Prepared) -> torch.Tensor:
    """``(K, D, D)`` world-axis penalty matrices of the frames' weak directions at their warm-start
    rotations (`losses.weak_directions`); normals by PCA when the Chamfer term computed none."""
    d = prep.dim
    points = prep.points.detach().cpu().numpy()
    normals = None if prep.normals is None else prep.normals.detach().cpu().numpy()
    local = np.stack(
        [
            losses.weak_directions(
                normals[a:b] if normals is not None else losses.frame_normals(points[a:b].astype(np.float64))
            )
            for a, b in zip(prep.starts[:-1], prep.starts[1:], strict=True)
        ]
    )
    rot = prep.init[:, :d, :d].detach().cpu().double().numpy()
    world = np.einsum("kij,kjl,kml->kim", rot, local, rot)
    return torch.as_tensor(world, dtype=prep.init.dtype, device=prep.init.device)


def temporal_pairs(frames: np.ndarray, window: int) -> np.ndarray:
    """Ordered pairs of positions ``(a, b)`` in ``frames`` with ``0 < |frames[a] - frames[b]| <= window``."""
    a, b = np.nonzero(np.abs(frames[:, None] - frames[None, :]) <= window)
    keep = a != b
    return np.stack([a[keep], b[keep]], 1).astype(np.int64)
