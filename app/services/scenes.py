"""Scenes: an upload read once, and a job's frames, in the project's ``.npz`` format.

An upload is read once, by the isolated reader within the service's limits, with its own frame
selection, into ``scene.npz`` in its folder (`UPLOAD_SCENE`, exact: float64 and the reader's
meta): jobs register that file, read as the command line reads any input
(`strep_core.runner.load_input`). A job's worker selects the run's frames and writes them to
``scene.npz`` in the job's folder before the method starts (`write_scene`, atomic). The live
viewer and the comparison recordings read that file (`read_scene`), so the API process never
parses an uploaded input. Both are the project's own ``.npz`` format (`strep_core.io.npz`),
uncompressed: points (a job's: float32), frames, origins, indices, unit, name, ground truth,
sensor and colours.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

SCENE = "scene.npz"
UPLOAD_SCENE = "scene.npz"  # in an upload's folder, beside the file as uploaded


def write_scene(seq: Any, path: str | Path, *, exact: bool = False) -> Path:
    """Write the `Sequence` ``seq`` to ``path`` (a temporary name, then renamed into place);
    ``exact``: float64 and the reader's meta (an upload's scene, which jobs register)."""
    from strep_core.io.npz import write_npz

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_npz(seq, path, compressed=False, exact=exact)
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
