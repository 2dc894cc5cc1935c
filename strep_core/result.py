"""The `Result` every method returns, and the fused map built from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.config import RunConfig
from strep_core.sequence import Sequence


@dataclass
class Result:
    """Poses found by one method on one sequence, with metrics and timings.

    Attributes:
        method: registry name of the method.
        sequence: the (selected) input sequence.
        poses: ``(K, D+1, D+1)`` estimated local -> world poses.
        initial_guess: what the method started from (``identity``, ``odometry``, ``icp``...).
        initial_poses: ``(K, D+1, D+1)`` those starting poses.
        metrics: flat dict; ``ate``/``point_l2`` etc. when ground truth exists, ``None`` else.
        timings: seconds per stage, ``wall_seconds`` the whole run.
        iterations: optimiser iterations (0 for one-pass methods).
        config: the run configuration used.
        history: per-event records (iteration, losses, ate) for loss curves.
        artifacts: extra outputs by name (e.g. a trained model's state).
    """

    method: str
    sequence: Sequence
    poses: np.ndarray
    initial_guess: str
    initial_poses: np.ndarray
    metrics: dict[str, Any]
    timings: dict[str, float]
    iterations: int
    config: RunConfig
    history: list[dict[str, Any]] = field(default_factory=list)
    artifacts: dict[str, Any] = field(default_factory=dict)

    def fused_map(self, *, max_points: int | None = None, poses: np.ndarray | None = None) -> np.ndarray:
        """All frames placed by the estimated poses: ``(M, D)``; see `fuse`."""
        return fuse(self.sequence.frames, self.poses if poses is None else poses, max_points=max_points)

    def frame_labels(self, *, max_points: int | None = None) -> np.ndarray:
        """Frame number of each point of `fused_map` (same subsampling), ``(M,)`` int."""
        labels = [np.full(len(f), i) for i, f in enumerate(self.sequence.frames)]
        out = np.concatenate(labels)
        return out[_stride_index(len(out), max_points)]


def _stride_index(n: int, max_points: int | None) -> slice:
    if max_points is None or n <= max_points:
        return slice(None)
    return slice(None, None, int(np.ceil(n / max_points)))


def fuse(frames: list[np.ndarray], poses: np.ndarray, *, max_points: int | None = None) -> np.ndarray:
    """Concatenate frames ``(N_i, D)`` placed by ``poses (K, D+1, D+1)`` into ``(M, D)``.

    ``max_points`` keeps an evenly strided subset (deterministic) when the map is larger.
    """
    out = np.concatenate([g.apply(p, f) for f, p in zip(frames, poses, strict=True)])
    return out[_stride_index(len(out), max_points)]
