"""Writers of result files: TUM trajectories, fused PLY maps, JSON metrics and configs.

Every writer writes to a temporary file in the destination folder and moves it into place
with `os.replace`, so a reader never sees a half-written file (and an interrupted write
leaves the previous version intact).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.errors import FormatError

__all__ = ["atomic_write", "to_jsonable", "write_json", "write_ply", "write_tum"]


def atomic_write(path: str | Path, data: bytes | str) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder + `os.replace`).

    Text is encoded as UTF-8. The parent folder must exist. Returns the path written.
    """
    path = Path(path)
    payload = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _fmt(x: float) -> str:
    return f"{x:.12g}"


def write_tum(path: str | Path, poses: np.ndarray, indices: np.ndarray | None = None) -> Path:
    """Write poses as a TUM trajectory: one line ``index tx ty tz qx qy qz qw`` per frame.

    Args:
        path: the file to write (``.txt`` or ``.tum``).
        poses: ``(K, 3, 3)`` SE(2) or ``(K, 4, 4)`` SE(3) poses, local -> world, in the
            sequence unit. 2D poses are written with ``z = 0`` and a yaw-only quaternion.
        indices: ``(K,)`` each frame's original index, written as the TUM time stamp
            (default ``0..K-1``). `strep_core.io.poses.read_tum` reads the file back.

    Raises:
        FormatError: ``poses`` or ``indices`` have the wrong shape, or poses are not finite.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((3, 3), (4, 4)):
        raise FormatError(f"{path}: poses have shape {poses.shape}; expected (K, 3, 3) or (K, 4, 4)")
    if not np.isfinite(poses).all():
        raise FormatError(f"{path}: poses contain non-finite values")
    k = len(poses)
    idx = np.arange(k) if indices is None else np.asarray(indices)
    if idx.shape != (k,):
        raise FormatError(f"{path}: {idx.size} indices for {k} poses")
    se3 = g.to_se3(poses)
    quats = g.rotation_to_quaternion(se3[:, :3, :3])
    lines = ["# index tx ty tz qx qy qz qw"]
    for i, t, q in zip(idx, se3[:, :3, 3], quats, strict=True):
        lines.append(" ".join([str(int(i)), *map(_fmt, t), *map(_fmt, q)]))
    return atomic_write(path, "\n".join(lines) + "\n")


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> Path:
    """Write a point cloud (a fused map) as a binary little-endian PLY.

    Args:
        points: ``(N, 2)`` or ``(N, 3)`` coordinates in the sequence unit; 2D points get
            ``z = 0``. Stored as float32.
        colors: optional ``(N, 3)`` RGB, uint8 (0-255) or float in ``[0, 1]``.

    Raises:
        FormatError: wrong shapes, non-finite points, or colours out of range.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise FormatError(f"{path}: points have shape {pts.shape}; expected (N, 2) or (N, 3)")
    pts = g.pad_points(pts.astype(np.float64))
    if not np.isfinite(pts).all():
        raise FormatError(f"{path}: points contain non-finite values")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    rgb: np.ndarray | None = None
    if colors is not None:
        col = np.asarray(colors)
        if col.shape != (len(pts), 3):
            raise FormatError(f"{path}: colors have shape {col.shape}; expected {(len(pts), 3)}")
        if np.issubdtype(col.dtype, np.floating):
            if col.size and not (np.isfinite(col).all() and col.min() >= 0.0 and col.max() <= 1.0):
                raise FormatError(f"{path}: float colors must lie in [0, 1]")
            col = np.round(col * 255.0)
        elif col.size and (col.min() < 0 or col.max() > 255):
            raise FormatError(f"{path}: integer colors must lie in 0..255")
        rgb = col.astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(len(pts), dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if rgb is not None:
        rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by STREP Studio",
        f"element vertex {len(pts)}",
        "property float x",
        "property float y",
        "property float z",
    ]
    if rgb is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    return atomic_write(path, ("\n".join(header) + "\n").encode("ascii") + rec.tobytes())


def to_jsonable(obj: Any) -> Any:
    """Convert ``obj`` into plain JSON types.

    numpy scalars and arrays become numbers and (nested) lists, NaN and infinities become
    ``None`` (JSON ``null``), paths become strings, tuples and sets become lists, mapping
    keys become strings, and pydantic models are dumped with ``model_dump(mode="json")``.

    Raises:
        FormatError: an object of a type that has no JSON form.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        items = sorted(obj, key=repr) if isinstance(obj, (set, frozenset)) else obj
        return [to_jsonable(v) for v in items]
    if hasattr(obj, "model_dump"):
        return to_jsonable(obj.model_dump(mode="json"))
    raise FormatError(f"cannot write a {type(obj).__name__} as JSON")


def write_json(path: str | Path, obj: Any, *, indent: int | None = 2) -> Path:
    """Write ``obj`` as UTF-8 JSON (metrics.json, config.json), converted by `to_jsonable`.

    NaN and infinities are written as ``null``; the output is strict JSON.
    """
    try:
        text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False, ensure_ascii=False)
    except FormatError as exc:
        raise FormatError(f"{path}: {exc}") from exc
    return atomic_write(path, text + "\n")
