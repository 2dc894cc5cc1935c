"""A job's scene: the frames its worker registers, written once by the worker, read by the rest.

The worker reads the upload (in its own process, within the service's limits), selects the
run's frames, and writes them to ``scene.npz`` in the job's folder before the method starts
(`write_scene`, atomic). The live viewer and the comparison recordings read that file
(`read_scene`), so the API process never parses an uploaded input.

Keys: ``points`` ``(M, D)`` float32 and ``counts`` ``(K,)`` (the frames, concatenated),
``origins`` ``(K, D)``, ``indices`` ``(K,)`` (frame indices in the input), ``unit``, ``name``,
optional ``poses`` ``(K, D+1, D+1)`` (ground truth) and ``colors`` ``(M, 3)`` uint8.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

SCENE = "scene.npz"


def write_scene(seq: Any, path: str | Path) -> Path:
    """Write the `Sequence` ``seq`` to ``path`` (a temporary name, then renamed into place)."""
    import numpy as np

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {
        "points": np.concatenate(seq.frames).astype(np.float32),
        "counts": np.array([len(f) for f in seq.frames], dtype=np.int64),
        "origins": np.asarray(seq.origins, dtype=np.float64),
        "indices": np.asarray(seq.indices, dtype=np.int64),
        "unit": np.array(seq.unit),
        "name": np.array(seq.name),
    }
    if seq.poses is not None:
        arrays["poses"] = np.asarray(seq.poses, dtype=np.float64)
    if seq.colors is not None:
        arrays["colors"] = np.concatenate(seq.colors).astype(np.uint8)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)
    return path


def read_scene(path: str | Path) -> Any:
    """The `Sequence` written by `write_scene` (no pickles; ``FileNotFoundError`` if absent)."""
    import numpy as np

    from strep_core.sequence import Sequence

    with np.load(Path(path), allow_pickle=False) as data:
        counts = data["counts"]
        cuts = np.cumsum(counts)[:-1]
        frames = np.split(data["points"].astype(np.float64), cuts)
        colors = np.split(data["colors"], cuts) if "colors" in data else None
        return Sequence(
            frames=frames,
            name=str(data["name"]),
            unit=str(data["unit"]),  # type: ignore[arg-type]
            origins=data["origins"],
            poses=data.get("poses"),
            indices=data["indices"],
            colors=colors,
            meta={"source": str(path), "format": "scene"},
        )
