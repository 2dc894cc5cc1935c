"""The `Result` every run returns, the fused map built from it, and the files written for it.

Files written to a run's output folder by `write_outputs` (each to a temporary name, then
renamed into place):

* ``trajectory.tum``: ``index tx ty tz qx qy qz qw`` per frame (2D: z = 0, yaw quaternion);
* ``map.ply``: the fused map, coloured by frame;
* ``metrics.json``: method, frames, ATE, point L2, RPE, wall seconds and more;
* ``config.json``: the `RunConfig` used;
* ``model.pt``: the trained model, for learned methods (reusable with ``--from-model``).
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.config import RunConfig
from strep_core.sequence import Sequence


@dataclass
class Result:
    """Poses found by one method on one sequence, with metrics and timings.

    Attributes:
        method: the method's name in the table (`strep_core.methods`).
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
        files: the files `write_outputs` wrote for it, by name (empty until written).
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
    files: dict[str, Path] = field(default_factory=dict)

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


# --------------------------------------------------------------------------------------------
# Result files

MAP_MAX_POINTS = 2_000_000  # cap of map.ply; larger maps are evenly strided


def frame_colors(labels: np.ndarray, num_frames: int) -> np.ndarray:
    """A distinct uint8 RGB colour per frame (hue along the sequence): ``(M,)`` -> ``(M, 3)``."""
    hues = np.arange(num_frames) / max(num_frames, 1) * 0.85
    palette = np.array([colorsys.hsv_to_rgb(h, 0.75, 0.95) for h in hues])
    return (palette[labels] * 255).astype(np.uint8)


OUTPUT_FILES = ("trajectory.tum", "map.ply", "metrics.json", "config.json", "matches.json", "model.pt")
"""Every file `write_outputs` may write; the service serves these names and no others."""


def write_outputs(result: Result, out_dir: str | Path) -> dict[str, Path]:
    """Write the result files of `result` into ``out_dir`` (created); returns them by name."""
    from strep_core.io.writers import write_json, write_ply, write_tum

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seq = result.sequence
    files = {
        "trajectory.tum": out / "trajectory.tum",
        "map.ply": out / "map.ply",
        "metrics.json": out / "metrics.json",
        "config.json": out / "config.json",
    }
    assert seq.indices is not None
    write_tum(files["trajectory.tum"], result.poses, seq.indices)
    points = result.fused_map(max_points=MAP_MAX_POINTS)
    labels = result.frame_labels(max_points=MAP_MAX_POINTS)
    write_ply(files["map.ply"], points, frame_colors(labels, len(seq)))
    write_json(files["metrics.json"], result.metrics)
    write_json(files["config.json"], result.config.model_dump(mode="json"))
    matches = result.artifacts.get("matches")
    if matches is not None:  # the front ends' verdicts, scores and covariances
        files["matches.json"] = out / "matches.json"
        write_json(files["matches.json"], matches)
    model = result.artifacts.get("model")
    if model is not None:
        from strep_core.artifacts import save_model

        files["model.pt"] = out / "model.pt"
        save_model(model, files["model.pt"])
    assert set(files) <= set(OUTPUT_FILES), sorted(files)
    return files
