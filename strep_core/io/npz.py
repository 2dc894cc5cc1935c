"""``.npz`` interchange format, the simplest way in and out of STREP Studio.

Keys (all lengths in the sequence unit):

============== ============================ ==============================================
key            shape / type                 meaning
============== ============================ ==============================================
points         (M, D) float                 all frames' local points, concatenated
counts         (K,) int                     points per frame (sums to M)
frames         (K, N, D) float              alternative to points + counts when every
                                            frame has N points
poses          (K, D+1, D+1) float          optional ground-truth poses, local -> world
initial_poses  (K, D+1, D+1) float          optional initial guess (odometry)
origins        (K, D) float                 optional sensor origin per frame (default 0)
indices        (K,) int                     optional original frame indices
unit           str                          optional ``"px"`` or ``"m"`` (default ``"m"``)
name           str                          optional name
============== ============================ ==============================================

Files are read with ``allow_pickle=False``: object arrays are refused.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from strep_core.errors import FormatError, SequenceError
from strep_core.sequence import FrameSelection, Sequence


def read_npz(path: str | Path, *, frames: str | FrameSelection | None = None) -> Sequence:
    """Read a sequence from an ``.npz`` file (keys above)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise FormatError(f"{path}: not a readable .npz file ({exc})") from exc
    if "points" in data and "counts" in data:
        counts = np.asarray(data["counts"]).astype(np.int64)
        pts = np.asarray(data["points"])
        if counts.ndim != 1 or (counts < 0).any() or counts.sum() != len(pts):
            raise FormatError(f"{path}: 'counts' must be non-negative and sum to len(points) = {len(pts)}")
        chunks = np.split(pts, np.cumsum(counts)[:-1])
    elif "frames" in data:
        arr = np.asarray(data["frames"])
        if arr.ndim != 3:
            raise FormatError(f"{path}: 'frames' must have shape (K, N, D), not {arr.shape}")
        chunks = list(arr)
    else:
        raise FormatError(f"{path}: needs keys 'points' and 'counts', or 'frames'")
    unit = str(data["unit"]) if "unit" in data else "m"
    name = str(data["name"]) if "name" in data else path.stem
    try:
        seq = Sequence(
            frames=chunks,
            name=name,
            unit=unit,  # type: ignore[arg-type]
            origins=data.get("origins"),
            poses=data.get("poses"),
            initial_poses=data.get("initial_poses"),
            indices=data.get("indices"),
            meta={"source": str(path), "format": "npz"},
        )
    except (ValueError, TypeError) as exc:
        if isinstance(exc, SequenceError):
            raise SequenceError(f"{path}: {exc}") from exc
        raise FormatError(f"{path}: {exc}") from exc
    return seq.select(frames) if frames else seq


def write_npz(seq: Sequence, path: str | Path, *, compressed: bool = True) -> None:
    """Write ``seq`` as ``.npz`` (points + counts layout, float32 points)."""
    arrays: dict[str, np.ndarray] = {
        "points": np.concatenate(seq.frames).astype(np.float32),
        "counts": np.array([len(f) for f in seq.frames], dtype=np.int64),
        "origins": np.asarray(seq.origins, dtype=np.float32),
        "indices": np.asarray(seq.indices),
        "unit": np.array(seq.unit),
        "name": np.array(seq.name),
    }
    if seq.poses is not None:
        arrays["poses"] = seq.poses
    if seq.initial_poses is not None:
        arrays["initial_poses"] = seq.initial_poses
    save = np.savez_compressed if compressed else np.savez
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    save(tmp, **arrays)
    tmp.replace(path)
