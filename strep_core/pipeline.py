"""Load an input, run a method, write the result files: what `strep run` and the service share.

Files written to the output folder (each to a temporary name, then renamed into place):

* ``trajectory.tum``: ``index tx ty tz qx qy qz qw`` per frame (2D: z = 0, yaw quaternion);
* ``map.ply``: the fused map, coloured by frame;
* ``metrics.json``: method, frames, ATE, point L2, RPE, wall seconds and more;
* ``config.json``: the `RunConfig` used;
* ``model.pt``: the trained model, for learned methods (reusable with ``--from-model``).
"""

from __future__ import annotations

import colorsys
import time
from pathlib import Path
from typing import Any

import numpy as np

from strep_core.config import RunConfig
from strep_core.events import CancelFlag, NullSink, Sink, StageEvent
from strep_core.result import Result
from strep_core.sequence import FrameSelection, Sequence

MAP_MAX_POINTS = 2_000_000  # cap of map.ply; larger maps are evenly strided


def load_input(
    source: str | Path, *, frames: str | FrameSelection | None = None, options: dict[str, Any] | None = None
) -> Sequence:
    """Read ``source``: a path in any supported format, or ``sample:NAME`` for a bundled sample;
    ``options`` go to the reader (`RunConfig.data`)."""
    from strep_core import samples
    from strep_core.io import load_sequence

    text = str(source)
    if samples.is_sample(text):
        return samples.load_sample(text.split(":", 1)[1], frames=frames)
    return load_sequence(text, frames=frames, **(options or {}))


def frame_colors(labels: np.ndarray, num_frames: int) -> np.ndarray:
    """A distinct uint8 RGB colour per frame (hue along the sequence): ``(M,)`` -> ``(M, 3)``."""
    hues = np.arange(num_frames) / max(num_frames, 1) * 0.85
    palette = np.array([colorsys.hsv_to_rgb(h, 0.75, 0.95) for h in hues])
    return (palette[labels] * 255).astype(np.uint8)


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
    model = result.artifacts.get("model")
    if model is not None:
        from strep_core.optimize import save_model

        files["model.pt"] = out / "model.pt"
        save_model(model, files["model.pt"])
    return files


def run_input(
    source: str | Path,
    config: RunConfig,
    *,
    out_dir: str | Path | None = None,
    sink: Sink | None = None,
    cancel: CancelFlag | None = None,
) -> Result:
    """Load ``source`` (applying ``config.frames``), run ``config.method``, write files if asked."""
    from strep_core.methods import run

    sink = sink or NullSink()
    started = time.perf_counter()
    sink.emit(StageEvent(stage="load", elapsed=0.0))
    seq = load_input(source, frames=config.frames, options=config.data.options())
    result = run(seq, config.model_copy(update={"frames": None}), sink=sink, cancel=cancel)
    result.config = result.config.model_copy(update={"frames": config.frames})  # the profile chosen kept
    if out_dir is not None:
        sink.emit(StageEvent(stage="write", elapsed=time.perf_counter() - started))
        write_outputs(result, out_dir)
    return result
