"""A job's scene: the frames its worker registers, written once by the worker, read by the rest.

The worker reads the upload (in its own process, within the service's limits), selects the
run's frames, and writes them to ``scene.npz`` in the job's folder before the method starts
(`write_scene`, atomic). The live viewer and the comparison recordings read that file
(`read_scene`), so the API process never parses an uploaded input. The file is the project's
own ``.npz`` format (`strep_core.io.npz`), uncompressed: points (float32), frames, origins,
indices, unit, name, ground truth, sensor and colours.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

SCENE = "scene.npz"


def write_scene(seq: Any, path: str | Path) -> Path:
    """Write the `Sequence` ``seq`` to ``path`` (a temporary name, then renamed into place)."""
    from strep_core.io.npz import write_npz

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_npz(seq, path, compressed=False)
    return path


def read_scene(path: str | Path) -> Any:
    """The `Sequence` written by `write_scene` (``FileNotFoundError`` if absent)."""
    from strep_core.io.limits import ReadBudget
    from strep_core.io.npz import read_npz

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    # written by the job's own worker from an input already read within the service's limits
    return read_npz(path, budget=ReadBudget(max_inflated_bytes=sys.maxsize, max_points=sys.maxsize))
