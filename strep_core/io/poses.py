"""Pose files: TUM and KITTI trajectories.

* TUM: one line ``stamp tx ty tz qx qy qz qw`` per pose (``#`` starts a comment); the
  quaternion is ``(x, y, z, w)`` and the pose maps the sensor frame into the world.
  `write_tum` writes each frame's original index as the stamp, so trajectories written by
  STREP Studio read back with their frame indices.
* KITTI: one line of 12 numbers per pose, the top 3 x 4 block of the pose, row-major.

Poses are returned as ``(K, 4, 4)`` homogeneous matrices (local -> world) in the file's
unit, or ``(K, 3, 3)`` when ``dim=2`` is asked for and every pose is planar.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from strep_core import geometry as g
from strep_core.errors import FormatError
from strep_core.io.writers import write_tum

__all__ = [
    "POSE_FILE_NAMES",
    "Trajectory",
    "associate",
    "find_pose_file",
    "read_kitti",
    "read_poses",
    "read_tum",
    "to_planar",
    "write_tum",
]

PoseFormat = Literal["auto", "tum", "kitti"]

#: File names looked for, in this order, when a folder's pose file is auto-detected.
POSE_FILE_NAMES = ("poses.txt", "groundtruth.txt", "gt_poses.txt", "trajectory.txt", "poses.tum")
_POSE_SUFFIXES = (".tum", ".kitti")
_SPLIT = re.compile(r"[\s,]+")


class Trajectory(NamedTuple):
    """Poses read from a file.

    Attributes:
        stamps: ``(K,)`` float time stamps (TUM) or ``None`` (KITTI has none).
        poses: ``(K, 4, 4)`` (or ``(K, 3, 3)`` when read with ``dim=2``), local -> world.
    """

    stamps: np.ndarray | None
    poses: np.ndarray


def _rows(path: Path) -> list[tuple[int, list[float]]]:
    """Numbers of every non-comment line, with 1-based line numbers."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a text pose file ({exc.reason} at byte {exc.start})") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read pose file ({exc.strerror or exc})") from exc
    rows = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            rows.append((lineno, [float(v) for v in _SPLIT.split(line) if v]))
        except ValueError as exc:
            raise FormatError(f"{path}:{lineno}: not a line of numbers ({exc})") from exc
    if not rows:
        raise FormatError(f"{path}: pose file holds no poses")
    return rows


def to_planar(poses: np.ndarray, *, name: str = "poses", tol: float = 1e-6) -> np.ndarray:
    """SE(3) poses ``(K, 4, 4)`` that are planar (z = 0, yaw only) -> SE(2) ``(K, 3, 3)``.

    Raises:
        FormatError: a pose leaves the plane by more than ``tol`` (lengths or rotation terms).
    """
    poses = np.asarray(poses, dtype=np.float64)
    off = np.concatenate([poses[:, 2, :2], poses[:, :2, 2], (poses[:, 2, 2] - 1.0)[:, None], poses[:, 2, 3:4]], 1)
    bad = np.flatnonzero(np.abs(off).max(1) > tol)
    if len(bad):
        raise FormatError(f"{name}: pose {bad[0]} is not planar (z = 0, yaw only); cannot read it as 2D")
    out = np.zeros((len(poses), 3, 3))
    out[:, :2, :2] = poses[:, :2, :2]
    out[:, :2, 2] = poses[:, :2, 3]
    out[:, 2, 2] = 1.0
    return out


def read_tum(path: str | Path, *, dim: Literal[2, 3] = 3) -> Trajectory:
    """Read a TUM trajectory (``stamp tx ty tz qx qy qz qw`` per line).

    Args:
        dim: 3 returns ``(K, 4, 4)`` poses; 2 returns ``(K, 3, 3)`` and requires every pose
            to be planar (as written by `write_tum` for 2D sequences).

    Raises:
        FormatError: a line without exactly 8 numbers, a quaternion that is not a rotation,
            or a non-planar pose with ``dim=2``.
    """
    path = Path(path)
    rows = _rows(path)
    for lineno, vals in rows:
        if len(vals) != 8:
            raise FormatError(
                f"{path}:{lineno}: a TUM line has 8 numbers (stamp tx ty tz qx qy qz qw), not {len(vals)}"
            )
    arr = np.array([v for _, v in rows], dtype=np.float64)
    norms = np.linalg.norm(arr[:, 4:8], axis=1)
    bad = np.flatnonzero(~(np.isfinite(norms) & (np.abs(norms - 1.0) < 1e-2)))
    if len(bad):
        raise FormatError(f"{path}:{rows[bad[0]][0]}: quaternion has norm {norms[bad[0]]:.3g}, not 1")
    poses = np.tile(np.eye(4), (len(arr), 1, 1))
    poses[:, :3, :3] = g.quaternion_to_rotation(arr[:, 4:8])
    poses[:, :3, 3] = arr[:, 1:4]
    if dim == 2:
        poses = to_planar(poses, name=str(path))
    return Trajectory(arr[:, 0], poses)


def read_kitti(path: str | Path, *, dim: Literal[2, 3] = 3) -> Trajectory:
    """Read a KITTI pose file (12 numbers per line: the 3 x 4 pose, row-major).

    Raises:
        FormatError: a line without exactly 12 numbers, or a rotation block that is not a
            rotation (orthonormality off by more than 1e-3).
    """
    path = Path(path)
    rows = _rows(path)
    for lineno, vals in rows:
        if len(vals) != 12:
            raise FormatError(f"{path}:{lineno}: a KITTI line has 12 numbers (3 x 4 pose), not {len(vals)}")
    arr = np.array([v for _, v in rows], dtype=np.float64).reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (len(arr), 1, 1))
    poses[:, :3, :] = arr
    rot = poses[:, :3, :3]
    err = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero(~(err < 1e-3))
    if len(bad):
        raise FormatError(f"{path}:{rows[bad[0]][0]}: the 3 x 3 block is not a rotation")
    if dim == 2:
        poses = to_planar(poses, name=str(path))
    return Trajectory(None, poses)


def read_poses(path: str | Path, *, format: PoseFormat = "auto", dim: Literal[2, 3] = 3) -> Trajectory:
    """Read a TUM or KITTI pose file; ``format="auto"`` decides from the suffix
    (``.tum``, ``.kitti``) or else from the count of numbers on the first line (8 or 12)."""
    path = Path(path)
    if format == "auto":
        suffix = path.suffix.lower()
        if suffix in _POSE_SUFFIXES:
            format = "tum" if suffix == ".tum" else "kitti"
        else:
            count = len(_rows(path)[0][1])
            if count not in (8, 12):
                raise FormatError(f"{path}: pose lines have {count} numbers; expected 8 (TUM) or 12 (KITTI)")
            format = "tum" if count == 8 else "kitti"
    if format == "tum":
        return read_tum(path, dim=dim)
    if format == "kitti":
        return read_kitti(path, dim=dim)
    raise FormatError(f"{path}: unknown pose format {format!r}; expected 'auto', 'tum' or 'kitti'")


def find_pose_file(folder: Path) -> Path | None:
    """The pose file of a folder: one of `POSE_FILE_NAMES`, else the only ``*.tum`` or
    ``*.kitti`` file; ``None`` when there is none.

    Raises:
        FormatError: several ``*.tum`` / ``*.kitti`` files and none of the standard names.
    """
    for name in POSE_FILE_NAMES:
        if (folder / name).is_file():
            return folder / name
    found = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _POSE_SUFFIXES)
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise FormatError(f"{folder}: several pose files ({names}); pass the one to use explicitly")
    return found[0] if found else None


def associate(stamps: np.ndarray, targets: np.ndarray, *, max_dt: float, name: str = "poses") -> np.ndarray:
    """For each target time, the index of the nearest stamp (as TUM's ``associate.py``).

    Args:
        stamps: ``(M,)`` stamps of the pose file.
        targets: ``(K,)`` times of the frames (e.g. parsed from image file names).
        max_dt: the largest accepted gap, in the stamps' unit (seconds for TUM).

    Returns:
        ``(K,)`` int64 indices into ``stamps``.

    Raises:
        FormatError: a target has no stamp within ``max_dt``.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    targets = np.asarray(targets, dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    pos = np.clip(np.searchsorted(s, targets), 1, max(len(s) - 1, 1))
    left = np.clip(pos - 1, 0, len(s) - 1)
    right = np.clip(pos, 0, len(s) - 1)
    pick = np.where(np.abs(s[left] - targets) <= np.abs(s[right] - targets), left, right)
    gap = np.abs(s[pick] - targets)
    bad = np.flatnonzero(~(gap <= max_dt))
    if len(bad):
        raise FormatError(
            f"{name}: no pose within {max_dt:g} of frame time {targets[bad[0]]:.6f} "
            f"({len(bad)} of {len(targets)} frames unmatched)"
        )
    return order[pick].astype(np.int64)
