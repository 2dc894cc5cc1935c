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
sensor         str                          optional ``"laser"`` or ``"depth"`` (what took it)
vertical_axis  (3,) float                   optional: the sensor's up direction in its own
                                            frame (a level depth camera, OpenCV axes: 0 -1 0)
colors         (M, 3) uint8                 optional per-point colours (viewers only)
meta           str                          optional JSON object: what the reader recorded
                                            (``Sequence.meta``; its ``sensor`` wins over the
                                            two keys above)
============== ============================ ==============================================

Object arrays are refused (no pickles). Arrays are read in chunks, each charged to the read's
`strep_core.io.limits.ReadBudget`, after their headers' sizes and point counts are checked
against it: a small file that would inflate past the budget is refused before it is
inflated.
"""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np

from strep_core.errors import FormatError, SequenceError
from strep_core.io.limits import CHUNK, CountingReader, ReadBudget
from strep_core.sequence import FrameSelection, Sequence

POINT_KEYS = ("points", "frames")  # arrays of points: (..., D)


def _read_array(fobj: CountingReader, key: str, budget: ReadBudget, where: str) -> np.ndarray:
    """One ``.npy`` member: its header checked against the budget, then its data read in chunks."""
    version = np.lib.format.read_magic(fobj)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fobj)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fobj)
    else:
        raise FormatError(f"{where}: unsupported .npy version {version}")
    if dtype.hasobject:
        raise FormatError(f"{where}: object arrays are refused")
    count = math.prod(shape)
    budget.bytes_over(count * dtype.itemsize, where, declared=True)
    if key in POINT_KEYS and len(shape) >= 2:
        budget.take_points(math.prod(shape[:-1]), where)  # before the points are read
    flat = np.empty(count, dtype=dtype)
    view = memoryview(flat.view(np.uint8)) if flat.nbytes else memoryview(b"")  # type: ignore[arg-type]
    pos = 0
    while pos < len(view):
        got = fobj.readinto(view[pos : pos + CHUNK])
        if not got:
            raise FormatError(f"{where}: the array is truncated ({pos} of {len(view)} bytes)")
        pos += got
    return flat.reshape(shape[::-1]).T if fortran else flat.reshape(shape)


def _read_arrays(path: Path, budget: ReadBudget) -> dict[str, np.ndarray]:
    data: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                if info.is_dir() or not info.filename.endswith(".npy"):
                    continue
                key = info.filename[: -len(".npy")]
                where = f"{path}:{info.filename}"
                # unbuffered: a read-ahead would be charged on top of the declared size
                with zf.open(info) as raw, CountingReader(raw, budget, where) as fobj:
                    data[key] = _read_array(fobj, key, budget, where)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, NotImplementedError) as exc:
        if isinstance(exc, FormatError):
            raise
        raise FormatError(f"{path}: not a readable .npz file ({exc})") from exc
    return data


def read_npz(
    path: str | Path, *, frames: str | FrameSelection | None = None, budget: ReadBudget | None = None
) -> Sequence:
    """Read a sequence from an ``.npz`` file (keys above) within ``budget`` (default: the
    library's limits)."""
    path = Path(path)
    data = _read_arrays(path, budget or ReadBudget())
    if "points" in data and "counts" in data:
        counts = np.asarray(data["counts"]).astype(np.int64)
        pts = np.asarray(data["points"])
        if counts.ndim != 1 or (counts < 0).any() or counts.sum() != len(pts):
            raise FormatError(f"{path}: 'counts' must be non-negative and sum to len(points) = {len(pts)}")
        cuts = np.cumsum(counts)[:-1]
        chunks = np.split(pts, cuts) if len(counts) else []  # no counts: no frames
    elif "frames" in data:
        arr = np.asarray(data["frames"])
        if arr.ndim != 3:
            raise FormatError(f"{path}: 'frames' must have shape (K, N, D), not {arr.shape}")
        chunks = list(arr)
        cuts = np.cumsum([len(c) for c in chunks])[:-1]
    else:
        raise FormatError(f"{path}: needs keys 'points' and 'counts', or 'frames'")
    unit = str(data["unit"]) if "unit" in data else "m"
    name = str(data["name"]) if "name" in data else path.stem
    meta: dict[str, object] = {"source": str(path), "format": "npz"}
    if "sensor" in data:  # what the sensor was (`strep_core.profiles` reads it)
        sensor: dict[str, object] = {"kind": str(data["sensor"])}
        if "vertical_axis" in data:
            axis = np.asarray(data["vertical_axis"], dtype=np.float64).reshape(-1)
            if axis.shape != (3,) or not np.isfinite(axis).all() or not np.linalg.norm(axis) > 0:
                raise FormatError(f"{path}: 'vertical_axis' must be 3 finite numbers, not all 0")
            sensor["vertical_axis"] = [float(c) for c in axis]
        meta["sensor"] = sensor
    if "meta" in data:
        try:
            recorded = json.loads(str(data["meta"]))
        except json.JSONDecodeError as exc:
            raise FormatError(f"{path}: 'meta' is not JSON ({exc})") from exc
        if not isinstance(recorded, dict):
            raise FormatError(f"{path}: 'meta' must be a JSON object")
        meta = {**recorded, **{k: v for k, v in meta.items() if k != "sensor"}}
    try:
        seq = Sequence(
            frames=chunks,
            name=name,
            unit=unit,  # type: ignore[arg-type]
            origins=data.get("origins"),
            poses=data.get("poses"),
            initial_poses=data.get("initial_poses"),
            indices=data.get("indices"),
            colors=np.split(np.asarray(data["colors"], dtype=np.uint8), cuts) if "colors" in data else None,
            meta=meta,
        )
    except (ValueError, TypeError) as exc:
        if isinstance(exc, SequenceError):
            raise SequenceError(f"{path}: {exc}") from exc
        raise FormatError(f"{path}: {exc}") from exc
    return seq.select(frames) if frames else seq


def write_npz(seq: Sequence, path: str | Path, *, compressed: bool = True, exact: bool = False) -> None:
    """Write ``seq`` as ``.npz`` (points + counts layout, float32 points).

    ``exact``: float64 points and origins and the reader's whole ``meta`` (JSON), so the file
    reads back as the very sequence written (the service's stored uploads)."""
    dtype = np.float64 if exact else np.float32
    arrays: dict[str, np.ndarray] = {
        "points": np.concatenate(seq.frames).astype(dtype),
        "counts": np.array([len(f) for f in seq.frames], dtype=np.int64),
        "origins": np.asarray(seq.origins, dtype=dtype),
        "indices": np.asarray(seq.indices),
        "unit": np.array(seq.unit),
        "name": np.array(seq.name),
    }
    if seq.poses is not None:
        arrays["poses"] = seq.poses
    if seq.initial_poses is not None:
        arrays["initial_poses"] = seq.initial_poses
    if seq.colors is not None:
        arrays["colors"] = np.concatenate(seq.colors).astype(np.uint8)
    sensor = seq.meta.get("sensor") if isinstance(seq.meta, dict) else None
    if isinstance(sensor, dict) and sensor.get("kind") in ("laser", "depth"):
        arrays["sensor"] = np.array(sensor["kind"])
        if sensor.get("vertical_axis") is not None:
            arrays["vertical_axis"] = np.asarray(sensor["vertical_axis"], dtype=np.float64)
    if exact and isinstance(seq.meta, dict):
        arrays["meta"] = np.array(
            json.dumps({k: v for k, v in seq.meta.items() if k not in ("source", "format")}, default=str)
        )
    save = np.savez_compressed if compressed else np.savez
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    save(tmp, **arrays)
    tmp.replace(path)
