"""A folder of point-cloud frames (``.ply`` / ``.pcd``), with an optional pose file.

* Frames are the folder's ``*.ply``, ``*.pcd`` and Velodyne ``*.bin`` files (KITTI's
  ``velodyne/`` folders: float32 x y z reflectance), sorted naturally by name (``frame2``
  before ``frame10``). PCD (ascii, binary) and PLY are parsed here with every per-point field
  (`strep_core.io.pcd`, `strep_core.io.ply`); other layouts (``binary_compressed`` PCD, PLY
  meshes) are read with Open3D (points, colours, normals).
* Per-point fields beyond x y z that every frame has (a LiDAR's intensity, ring, time;
  normals, curvature) are kept in ``meta["point_fields"]`` (their names) and
  ``meta["point_attributes"]`` (one dict of arrays per frame, aligned with the frame's points
  and with ``meta["files"]``). A per-point time field of absolute times (after 1973) gives each
  scan a timestamp, its earliest point's, in seconds: ``meta["stamps"]``.
* Frames are always 3D, even when every z is 0: a folder of PLY/PCD is a 3D format, and a
  reader that changed dimension with the content would be unpredictable. 2D data belongs
  in ``.npz`` (or the DeepMapping and CARMEN formats).
* Non-finite points (the holes of organised clouds) are dropped; ``meta["dropped_points"]``
  counts them.
* Colours, when every selected frame has them, fill ``Sequence.colors`` (uint8).
* Poses (local -> world, in the frames' unit): a TUM or KITTI file given as ``poses``, or
  found in the folder (`strep_core.io.poses.find_pose_file`). KITTI poses of ``.bin`` scans
  with a KITTI ``calib.txt`` beside them or one folder up are moved to the LiDAR's frame
  (``Tr^-1 P Tr``). They match the frames by
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

FRAME_SUFFIXES = (".ply", ".pcd", ".bin")
TIME_FIELDS = ("timestamp", "time", "t")  # a per-point time, first found wins
_EPOCH_1973 = 1e8  # seconds: larger per-point times are absolute, smaller ones offsets within a scan
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
    uint8 or ``None``, the count of non-finite points ``dropped``, and the other per-point
    ``fields`` (``(N,)`` or ``(N, c)`` arrays in the file's types, the rows of ``points``)."""

    points: np.ndarray
    colors: np.ndarray | None
    dropped: int
    fields: dict[str, np.ndarray] = {}  # noqa: RUF012 (a NamedTuple default, never mutated)


def _parsed(path: Path, data: bytes) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]] | None:
    """Points, colours and other fields of a PCD, PLY or Velodyne ``.bin`` file parsed here;
    ``None`` for a layout left to Open3D."""
    from strep_core.io.pcd import PcdLayoutError, parse_pcd_fields
    from strep_core.io.ply import PlyLayoutError, parse_ply_fields

    suffix = path.suffix.lower()
    if suffix == ".bin":
        if len(data) % 16:
            raise FormatError(f"{path}: a Velodyne .bin holds float32 x y z reflectance: {len(data)} bytes")
        table = np.frombuffer(data, dtype="<f4").reshape(-1, 4)
        return table[:, :3].astype(np.float64), None, {"reflectance": table[:, 3].copy()}
    try:
        fields = parse_pcd_fields(data, name=str(path)) if suffix == ".pcd" else parse_ply_fields(data, name=str(path))
    except (PcdLayoutError, PlyLayoutError):
        return None
    points = np.stack([fields.pop(a) for a in "xyz"], 1).astype(np.float64)
    colors = None
    if "rgb" in fields or "rgba" in fields:  # PCL packs 8-bit r, g, b into one 32-bit value
        packed = fields.pop("rgb" if "rgb" in fields else "rgba")
        bits = packed.astype(np.float32).view(np.uint32) if packed.dtype.kind == "f" else packed.astype(np.uint32)
        colors = np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], 1).astype(np.uint8)
    elif {"red", "green", "blue"} <= set(fields):
        rgb = [fields.pop(c) for c in ("red", "green", "blue")]
        scale = 255.0 if all(c.dtype.kind == "f" for c in rgb) and max(float(c.max()) for c in rgb) <= 1.0 else 1.0
        colors = np.clip(np.round(np.stack(rgb, 1) * scale), 0, 255).astype(np.uint8)
    return points, colors, fields


def scan_stamp(fields: dict[str, np.ndarray]) -> float | None:
    """A scan's timestamp in seconds from its per-point time field (`TIME_FIELDS`): the earliest
    point's, when the times are absolute (in s, ms, us or ns since 1970, told by their size);
    ``None`` when there is no such field or its times are offsets within the scan."""
    for name in TIME_FIELDS:
        if name in fields and np.size(fields[name]):
            first = float(np.min(fields[name]))
            for unit in (1e9, 1e6, 1e3, 1.0):  # ns, us, ms, s
                if first >= _EPOCH_1973 * unit:
                    return first / unit
            return None
    return None


def read_point_cloud(path: Path, budget: ReadBudget | None = None) -> Cloud:
    """Read one PLY, PCD or Velodyne ``.bin`` file, every per-point field kept (layouts not
    parsed here: Open3D, points and colours); non-finite points are dropped.

    With a ``budget``, the point count the file's header declares (a ``.bin``: its size) is
    checked against it before the file is read, and the points read are charged to it.

    Raises:
        FormatError: the file cannot be read or holds no points, or it declares more points
            than the budget has left.
    """
    if not path.is_file():
        raise FormatError(f"{path}: no such point-cloud file")
    with open(path, "rb") as f:
        head = f.read(64 * 1024)
    suffix = path.suffix.lower()
    if suffix == ".ply" and not head.startswith(b"ply"):  # else Open3D's RPly prints to stderr
        raise FormatError(f"{path}: not a PLY file (a PLY file starts with the line 'ply')")
    if budget is not None:
        declared = path.stat().st_size // 16 if suffix == ".bin" else declared_cloud_points(head)
        if declared is not None:
            budget.take_points(declared, str(path), declared=True)
    parsed = _parsed(path, path.read_bytes())
    fields: dict[str, np.ndarray] = {}
    if parsed is None:
        pts, colors = _read_open3d(path)
    else:
        pts, colors, fields = parsed
    if len(pts) == 0:
        raise FormatError(f"{path}: no points could be read (truncated or not a {path.suffix} file?)")
    ok = np.all(np.isfinite(pts), axis=1, keepdims=False).reshape(-1)
    dropped = int(ok.size - np.count_nonzero(ok))
    if dropped:
        pts = pts[ok]
        colors = None if colors is None else colors[ok]
        fields = {k: v[ok] for k, v in fields.items()}
    if budget is not None:
        budget.take_points(len(pts), str(path))
    return Cloud(pts, colors, dropped, fields)


def _read_open3d(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    from strep_core._open3d import o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(path)
    colors = None
    if cloud.has_colors():
        colors = np.round(np.clip(np.asarray(cloud.colors), 0.0, 1.0) * 255.0).astype(np.uint8)
    return np.asarray(cloud.points, dtype=np.float64), colors


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
        calib = _kitti_calibration(path) if all(f.suffix.lower() == ".bin" for f in files) else None
        if calib is not None and matched == "order" and read_poses(poses_path, format=poses_format).stamps is None:
            # KITTI's poses are its left camera's: the LiDAR's are Tr^-1 P Tr (p_cam = Tr p_velo)
            gt = np.linalg.inv(calib[1]) @ gt @ calib[1]
            pose_info["poses_frame"] = f"LiDAR, through Tr of {calib[0]}"

    budget = budget or ReadBudget()
    pts, cols, attrs = [], [], []
    dropped = 0
    for i in sel:
        cloud = read_point_cloud(files[i], budget)
        pts.append(cloud.points)
        cols.append(cloud.colors)
        attrs.append(cloud.fields)
        dropped += cloud.dropped
    colors = cols if cols and all(c is not None for c in cols) else None
    point_info = _point_fields(attrs, [files[i].suffix.lower() for i in sel])
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
                **point_info,
            },
        )
    except SequenceError as exc:
        raise SequenceError(f"{path}: {exc}") from exc


def _kitti_calibration(folder: Path) -> tuple[str, np.ndarray] | None:
    """``(path, Tr)`` of a KITTI ``calib.txt`` beside the scans or one folder up (``Tr:`` 12
    numbers, LiDAR -> left camera); ``None`` when there is none."""
    for place in (folder, folder.parent):
        calib = place / "calib.txt"
        if not calib.is_file():
            continue
        for line in calib.read_text(encoding="utf-8", errors="replace").splitlines():
            key, _, rest = line.partition(":")
            if key.strip() == "Tr":
                try:
                    values = np.array(rest.split(), dtype=np.float64)
                except ValueError as exc:
                    raise FormatError(f"{calib}: Tr is not 12 numbers ({exc})") from exc
                if values.shape != (12,) or not np.isfinite(values).all():
                    raise FormatError(f"{calib}: Tr has {values.size} numbers, not 12")
                return str(calib), np.vstack([values.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    return None


def _point_fields(attrs: list[dict[str, np.ndarray]], suffixes: list[str]) -> dict[str, object]:
    """The meta entries of the frames' per-point fields: the names every frame has, their
    arrays per frame, the scans' stamps when each has one; ``format`` velodyne-bin for ``.bin``."""
    out: dict[str, object] = {}
    if suffixes and all(s == ".bin" for s in suffixes):
        out["format"] = "velodyne-bin"
    if not attrs:
        return out
    names = [n for n in attrs[0] if all(n in a for a in attrs[1:])]
    if names:
        out["point_fields"] = names
        out["point_attributes"] = [{n: a[n] for n in names} for a in attrs]
    stamps = [scan_stamp(a) for a in attrs]
    if all(s is not None for s in stamps):
        out["stamps"] = stamps
    return out


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
