"""A folder of point-cloud frames (``.ply`` / ``.pcd``), with an optional pose file.

* Frames are the folder's ``*.ply`` and ``*.pcd`` files, sorted naturally by name
  (``frame2`` before ``frame10``); each is read with Open3D.
* Frames are always 3D, even when every z is 0: a folder of PLY/PCD is a 3D format, and a
  reader that changed dimension with the content would be unpredictable. 2D data belongs
  in ``.npz`` (or the DeepMapping and CARMEN formats).
* Non-finite points (the holes of organised clouds) are dropped; ``meta["dropped_points"]``
  counts them.
* Colours, when every selected frame has them, fill ``Sequence.colors`` (uint8).
* Poses (local -> world, in the frames' unit): a TUM or KITTI file given as ``poses``, or
  found in the folder (`strep_core.io.poses.find_pose_file`). They match the frames by
  order when the counts agree; otherwise TUM stamps match the number in each frame's name
  (as written by `strep_core.io.writers.write_tum`, which stamps each frame's index).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from strep_core.errors import FormatError, SequenceError
from strep_core.io.limits import ReadBudget, declared_cloud_points
from strep_core.io.poses import PoseFormat, associate, find_pose_file, read_poses
from strep_core.sequence import FrameSelection, Sequence, Unit

__all__ = ["FRAME_SUFFIXES", "Cloud", "list_frames", "natural_key", "read_conf", "read_folder", "read_point_cloud"]

FRAME_SUFFIXES = (".ply", ".pcd")
_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[object, ...]:
    """Sort key that orders embedded numbers by value: ``f2`` < ``f10``."""
    return tuple(int(p) if p.isdigit() else p.lower() for p in _DIGITS.split(name))


def list_frames(folder: Path) -> list[Path]:
    """The ``.ply`` / ``.pcd`` files directly in ``folder``, sorted naturally (hidden files skipped)."""
    files = [
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES and not p.name.startswith(".")
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


class Cloud(NamedTuple):
    """One frame read from a file: ``points`` ``(N, 3)`` float64, ``colors`` ``(N, 3)``
    uint8 or ``None``, and the count of non-finite points ``dropped``."""

    points: np.ndarray
    colors: np.ndarray | None
    dropped: int


def read_point_cloud(path: Path, budget: ReadBudget | None = None) -> Cloud:
    """Read one PLY/PCD file with Open3D; non-finite points are dropped.

    With a ``budget``, the point count the file's header declares is checked against it before
    Open3D reads (and inflates) the file, and the points read are charged to it.

    Raises:
        FormatError: Open3D cannot read the file or finds no points in it, or it declares
            more points than the budget has left.
    """
    from strep_core._open3d import o3d

    if not path.is_file():
        raise FormatError(f"{path}: no such point-cloud file")
    with open(path, "rb") as f:
        head = f.read(64 * 1024)
    if path.suffix.lower() == ".ply" and not head.startswith(b"ply"):  # else Open3D's RPly prints to stderr
        raise FormatError(f"{path}: not a PLY file (a PLY file starts with the line 'ply')")
    if budget is not None:
        declared = declared_cloud_points(head)
        if declared is not None:
            budget.take_points(declared, str(path), declared=True)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(path)
    pts = np.asarray(cloud.points, dtype=np.float64)
    if len(pts) == 0:
        raise FormatError(f"{path}: no points could be read (truncated or not a {path.suffix} file?)")
    colors = None
    if cloud.has_colors():
        colors = np.round(np.clip(np.asarray(cloud.colors), 0.0, 1.0) * 255.0).astype(np.uint8)
    ok = np.all(np.isfinite(pts), axis=1, keepdims=False).reshape(-1)
    dropped = int(ok.size - np.count_nonzero(ok))
    if dropped:
        pts = pts[ok]
        colors = None if colors is None else colors[ok]
    if budget is not None:
        budget.take_points(len(pts), str(path))
    return Cloud(pts, colors, dropped)


def _frame_number(path: Path) -> float:
    nums = _DIGITS.findall(path.stem)
    return float(nums[-1]) if nums else float("nan")


def _match_poses(poses_path: Path, fmt: PoseFormat, files: list[Path], folder: Path) -> tuple[np.ndarray, str]:
    traj = read_poses(poses_path, format=fmt)
    if len(traj.poses) == len(files):
        return traj.poses, "order"
    if traj.stamps is None:
        raise FormatError(f"{poses_path}: {len(traj.poses)} poses for {len(files)} frames in {folder}")
    numbers = np.array([_frame_number(p) for p in files])
    if not np.isfinite(numbers).all():
        raise FormatError(
            f"{poses_path}: {len(traj.poses)} poses for {len(files)} frames, and frame names "
            "carry no number to match the stamps"
        )
    idx = associate(traj.stamps, numbers, max_dt=1e-6, name=str(poses_path))
    return traj.poses[idx], "stamp"


def read_folder(
    path: str | Path,
    *,
    frames: str | FrameSelection | None = None,
    poses: str | Path | None = None,
    poses_format: PoseFormat = "auto",
    unit: Unit = "m",
    budget: ReadBudget | None = None,
) -> Sequence:
    """Read a folder of ``.ply`` / ``.pcd`` frames as a 3D sequence.

    Args:
        path: the folder.
        frames: ``start:stop[:step]`` over the naturally sorted files; only the selected
            files are read, and their positions are kept in ``Sequence.indices``.
        poses: a TUM or KITTI pose file (local -> world); default: auto-detected in the
            folder (``poses.txt``, ``groundtruth.txt``, ..., or a single ``*.tum`` /
            ``*.kitti``).
        poses_format: ``"auto"`` (from the suffix or the numbers per line), ``"tum"`` or ``"kitti"``.
        unit: the unit of the coordinates (``"m"`` by default).
        budget: the points the frames may hold (default: the library's limits).

    Returns:
        A `Sequence` of ``(N_i, 3)`` frames, with ``poses`` ``(K, 4, 4)`` when a pose file is
        given or found, and ``colors`` when every selected frame has colours.

    Raises:
        FormatError: no frame files, an unreadable frame, a malformed pose file, or poses
            that cannot be matched to the frames.
        SequenceError: too few frames or points, non-finite poses.
    """
    path = Path(path)
    if not path.is_dir():
        raise FormatError(f"{path}: not a folder of .ply / .pcd frames")
    files = list_frames(path)
    if not files:
        raise FormatError(f"{path}: no .ply or .pcd files in this folder")
    sel = FrameSelection.parse(frames).keep(len(files))

    gt = None
    pose_info: dict[str, object] = {}
    poses_path = Path(poses) if poses is not None else find_pose_file(path)
    if poses_path is not None:
        if not poses_path.is_file():
            raise FormatError(f"{poses_path}: no such pose file")
        all_poses, matched = _match_poses(poses_path, poses_format, files, path)
        gt = all_poses[sel]
        pose_info = {"poses_file": str(poses_path), "poses_matched_by": matched}

    budget = budget or ReadBudget()
    pts, cols = [], []
    dropped = 0
    for i in sel:
        cloud = read_point_cloud(files[i], budget)
        pts.append(cloud.points)
        cols.append(cloud.colors)
        dropped += cloud.dropped
    colors = cols if cols and all(c is not None for c in cols) else None
    try:
        return Sequence(
            frames=pts,
            name=path.name,
            unit=unit,
            poses=gt,
            indices=sel,
            colors=colors,  # type: ignore[arg-type]
            meta={
                "source": str(path),
                "format": "folder",
                "files": [files[i].name for i in sel],
                "dropped_points": dropped,
                **pose_info,
            },
        )
    except SequenceError as exc:
        raise SequenceError(f"{path}: {exc}") from exc


def _parse_conf(conf: Path) -> list[tuple[str, np.ndarray]]:
    """``(file name, 4 x 4 pose)`` of every ``bmesh`` line of a ``.conf`` file."""
    from strep_core import geometry as g

    try:
        text = conf.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{conf}: cannot read .conf file ({exc})") from exc
    scans = []
    for lineno, line in enumerate(text.splitlines(), 1):
        tokens = line.split()
        if not tokens or tokens[0] != "bmesh":
            continue
        if len(tokens) != 9:
            raise FormatError(
                f"{conf}:{lineno}: a bmesh line is 'bmesh FILE tx ty tz qx qy qz qw' "
                f"(8 fields after bmesh), not {len(tokens) - 1}"
            )
        try:
            vals = np.array(tokens[2:], dtype=np.float64)
        except ValueError as exc:
            raise FormatError(f"{conf}:{lineno}: bmesh pose is not 7 numbers ({exc})") from exc
        norm = float(np.linalg.norm(vals[3:]))
        if not (np.isfinite(vals).all() and abs(norm - 1.0) < 1e-2):
            raise FormatError(f"{conf}:{lineno}: bmesh pose has a quaternion of norm {norm:.3g}, not 1")
        pose = np.eye(4)
        # Stanford's convention: p_world = R(q)^T p + t, with R(q) from (qx, qy, qz, qw).
        pose[:3, :3] = g.quaternion_to_rotation(vals[3:]).T
        pose[:3, 3] = vals[:3]
        scans.append((tokens[1], pose))
    if not scans:
        raise FormatError(f"{conf}: no 'bmesh FILE tx ty tz qx qy qz qw' lines")
    return scans


def read_conf(
    path: str | Path,
    *,
    frames: str | FrameSelection | None = None,
    voxel: float | None = None,
    budget: ReadBudget | None = None,
) -> Sequence:
    """Read range scans listed in a Stanford ``.conf`` file (the Stanford bunny layout).

    Lines ``bmesh FILE tx ty tz qx qy qz qw`` name a scan (PLY, in the ``.conf``'s folder)
    and its reference pose; other lines (``camera``...) are ignored. The pose maps scan
    points to the common frame as ``p_world = R(q)^T p + t`` with ``R(q)`` the rotation of
    the quaternion ``(qx, qy, qz, qw)`` (equivalently, ``qw`` negated), checked on the bunny:
    every scan then lies about 0.25 mm from the others.

    Args:
        path: the ``.conf`` file, or a folder holding exactly one.
        frames: ``start:stop[:step]`` over the bmesh lines, in file order.
        voxel: optional voxel size (the data's unit, metres for the bunny) for Open3D
            voxel down-sampling of every scan.
        budget: the points the scans may hold, before down-sampling (default: the
            library's limits).

    Returns:
        A `Sequence` of ``(N_i, 3)`` scans with ``poses`` ``(K, 4, 4)``, scan -> world.

    Raises:
        FormatError: no or several ``.conf`` files, a malformed bmesh line, a missing or
            unreadable scan.
    """
    path = Path(path)
    conf = path
    if path.is_dir():
        confs = sorted(path.glob("*.conf"))
        if len(confs) != 1:
            raise FormatError(f"{path}: expected one .conf file, found {len(confs)}")
        conf = confs[0]
    if not conf.is_file():
        raise FormatError(f"{conf}: no such .conf file")
    if voxel is not None and not voxel > 0:
        raise FormatError(f"{conf}: voxel must be positive, not {voxel}")
    scans = _parse_conf(conf)
    sel = FrameSelection.parse(frames).keep(len(scans))
    for i in sel:
        scan = conf.parent / scans[i][0]
        if not scan.is_file():
            raise FormatError(f"{conf}: scan {scans[i][0]!r} listed in the file is missing ({scan})")
    budget = budget or ReadBudget()
    pts = []
    for i in sel:
        cloud = read_point_cloud(conf.parent / scans[i][0], budget)
        xyz = cloud.points
        if voxel is not None:
            from strep_core._open3d import o3d

            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
            xyz = np.asarray(pc.voxel_down_sample(voxel).points, dtype=np.float64)
        pts.append(xyz)
    try:
        return Sequence(
            frames=pts,
            name=conf.stem,
            unit="m",
            poses=np.stack([scans[i][1] for i in sel]) if len(sel) else None,
            indices=sel,
            meta={
                "source": str(conf),
                "format": "conf",
                "files": [scans[i][0] for i in sel],
                "voxel": voxel,
            },
        )
    except SequenceError as exc:
        raise SequenceError(f"{conf}: {exc}") from exc
