"""A sequence packed once per run for the learned loop: padded tensors on the run's device.

Lengths are divided by `Sequence.scale` (docs/design/warm-start.md). Frames are padded to the
widest one (``(K, N, D)`` with ``counts``) so every per-iteration operation has a static shape;
everything here is built once, before the first iteration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from strep_core import losses
from strep_core.config import RunConfig
from strep_core.neighbours import PAD, FrameIndex
from strep_core.sequence import Sequence


@dataclass
class Prepared:
    """A sequence as float32 tensors in normalised units, on the run's device.

    Attributes:
        dim: D.
        scale: the sequence's `scale` (length unit per normalised unit).
        points: ``(K, N, D)`` local points of every frame (working set), padded with `PAD`.
        counts: ``(K,)`` int64 real points per frame (host copy: ``counts_host``).
        normals: ``(K, N, D)`` local unit normals of ``points`` (``loss.chamfer="plane"``), else None.
        decoder_points: ``(K, Nd, D)`` the fixed decoder input of every frame.
        origins: ``(K, D)`` sensor origins, local.
        init: ``(K, D+1, D+1)`` warm-start poses, translations normalised.
        centre: ``(D,)`` normalised world centre of the warm-start trajectory (occupancy input
            is ``world - centre``).
        index: the frames' points, searchable (`strep_core.neighbours.FrameIndex`).
    """

    dim: int
    scale: float
    points: torch.Tensor
    counts: torch.Tensor
    counts_host: np.ndarray
    normals: torch.Tensor | None
    decoder_points: torch.Tensor
    origins: torch.Tensor
    init: torch.Tensor
    centre: torch.Tensor
    index: FrameIndex

    @property
    def num_frames(self) -> int:
        return len(self.counts_host)


def _strided(n: int, m: int | None) -> np.ndarray:
    """``min(n, m)`` evenly spread indices of ``range(n)``; ``m`` of them (repeating) if n < m."""
    if m is None or n == m:
        return np.arange(n)
    return np.floor(np.arange(m) * (n / m)).astype(np.int64)


def _padded(frames: list[np.ndarray], width: int, fill: float) -> np.ndarray:
    out = np.full((len(frames), width, frames[0].shape[1]), fill, dtype=np.float64)
    for k, f in enumerate(frames):
        out[k, : len(f)] = f
    return out


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
    counts = np.array([len(f) for f in frames], dtype=np.int64)
    width = int(counts.max())
    nd = config.model.decoder_points
    nd = width if nd is None else min(nd, width)
    dec = np.stack([f[_strided(len(f), nd)] for f in frames])
    init = np.array(init_poses, dtype=np.float64, copy=True)
    d = seq.dim
    init[:, :d, d] /= scale
    assert seq.origins is not None

    def f32(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=device)

    points = f32(_padded(frames, width, PAD))
    counts_t = torch.as_tensor(counts, device=device)
    normals = None
    if config.loss.chamfer == "plane":
        normals = f32(_padded([losses.frame_normals(f) for f in frames], width, 0.0))
    return Prepared(
        dim=d,
        scale=scale,
        points=points,
        counts=counts_t,
        counts_host=counts,
        normals=normals,
        decoder_points=f32(dec),
        origins=f32(seq.origins / scale),
        init=f32(init),
        centre=f32(init[:, :d, d].mean(0)),
        index=FrameIndex(points, counts_t),
    )


def weak_matrices(prep: Prepared) -> torch.Tensor:
    """``(K, D, D)`` world-axis penalty matrices of the frames' weak directions at their warm-start
    rotations (`losses.weak_directions`); normals by PCA when the Chamfer term computed none."""
    d = prep.dim
    n = prep.counts_host
    points = prep.points.detach().cpu().numpy()
    normals = None if prep.normals is None else prep.normals.detach().cpu().numpy()
    local = np.stack(
        [
            losses.weak_directions(
                normals[k, : n[k]]
                if normals is not None
                else losses.frame_normals(points[k, : n[k]].astype(np.float64))
            )
            for k in range(len(n))
        ]
    )
    rot = prep.init[:, :d, :d].detach().cpu().double().numpy()
    world = np.einsum("kij,kjl,kml->kim", rot, local, rot)
    return torch.as_tensor(world, dtype=prep.init.dtype, device=prep.init.device)
