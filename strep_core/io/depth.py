"""Folders of 16-bit depth images, back-projected to 3D points in the camera frame.

Two layouts are read:

* 7-Scenes: ``frame-NNNNNN.depth.png`` with optional ``frame-NNNNNN.pose.txt`` (4 x 4
  camera -> world, metres) and ``frame-NNNNNN.color.jpg``, intrinsics in
  ``camera-intrinsics.txt``.
* TUM RGB-D style: ``depth/*.png`` (or ``*.png`` in the folder itself) named by time stamp,
  optional ``rgb/`` or ``color/`` images and a ``groundtruth.txt`` TUM trajectory matched
  to the images by time stamp (nearest within 20 ms when names are time stamps) or by order
  (when the counts agree).

Pixels are subsampled with a stride (as the STREP paper does for the Active Vision
Dataset) and back-projected with the pinhole model: for a pixel ``(u, v)`` (column, row)
of depth ``z`` metres, ``x = (u - cx) z / fx``, ``y = (v - cy) z / fy`` (x right, y down,
z forward). Depth 0 and 65535 are invalid (no measurement).

Intrinsics come from the ``intrinsics`` argument or from a file in the folder:
``camera-intrinsics.txt`` / ``intrinsics.txt`` (a 3 x 3 K, or the 4 numbers
``fx fy cx cy``) or ``intrinsics.json`` (keys ``fx fy cx cy``, or ``K``).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from collections.abc import Sequence as Seq
from pathlib import Path

import numpy as np

from strep_core.errors import FormatError, SequenceError
from strep_core.io.folder import natural_key
from strep_core.io.limits import ReadBudget
from strep_core.io.poses import associate, read_tum
from strep_core.sequence import FrameSelection, Sequence

__all__ = ["INTRINSICS_FILES", "Intrinsics", "find_depth_images", "read_depth_folder", "read_intrinsics"]

INTRINSICS_FILES = ("camera-intrinsics.txt", "intrinsics.txt", "intrinsics.json")
INVALID_DEPTH = 65535  # Kinect "no reading" code, besides 0
MAX_DT = 0.02  # seconds: TUM's own association tolerance
_STAMP = re.compile(r"^\d+(\.\d+)?$")

Intrinsics = tuple[float, float, float, float]  # fx, fy, cx, cy in pixels


def _as_intrinsics(value: object, where: str) -> Intrinsics:
    """``(fx, fy, cx, cy)`` from 4 numbers, a 3 x 3 K, or a mapping."""
    if isinstance(value, Mapping):
        if "K" in value:
            return _as_intrinsics(value["K"], where)
        try:
            value = [value[k] for k in ("fx", "fy", "cx", "cy")]
        except KeyError as exc:
            raise FormatError(f"{where}: intrinsics need keys fx fy cx cy (or K), missing {exc}") from exc
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise FormatError(f"{where}: intrinsics are not numbers ({exc})") from exc
    if arr.size == 9:
        k = arr.reshape(3, 3)
        vals = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
    elif arr.size == 4:
        vals = list(arr.ravel())
    else:
        raise FormatError(f"{where}: intrinsics need a 3 x 3 K or fx fy cx cy, got {arr.size} numbers")
    fx, fy, cx, cy = (float(v) for v in vals)
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise FormatError(f"{where}: invalid intrinsics fx={fx} fy={fy} cx={cx} cy={cy}")
    return fx, fy, cx, cy


def read_intrinsics(path: str | Path) -> Intrinsics:
    """Read ``(fx, fy, cx, cy)`` in pixels from a text (3 x 3 K or 4 numbers) or JSON file.

    Raises:
        FormatError: unreadable file, not numbers, wrong count, non-positive focal lengths.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: cannot read intrinsics ({exc})") from exc
    if path.suffix.lower() == ".json":
        try:
            return _as_intrinsics(json.loads(text), str(path))
        except json.JSONDecodeError as exc:
            raise FormatError(f"{path}: intrinsics file is not valid JSON ({exc.msg})") from exc
    lines = [ln.split("#", 1)[0] for ln in text.splitlines()]
    tokens = " ".join(lines).replace(",", " ").split()
    try:
        numbers = [float(t) for t in tokens]
    except ValueError as exc:
        raise FormatError(f"{path}: intrinsics file holds something that is not a number ({exc})") from exc
    return _as_intrinsics(numbers, str(path))


def find_depth_images(folder: Path) -> tuple[list[Path], str]:
    """The depth images of a folder, sorted naturally, and the layout's name.

    ``*.depth.png`` in the folder ("7scenes"), else ``depth/*.png`` ("tum"), else
    ``*.png`` in the folder ("plain"). Returns ``([], "")`` when there is none.
    """
    found = sorted(folder.glob("*.depth.png"), key=lambda p: natural_key(p.name))
    if found:
        return found, "7scenes"
    if (folder / "depth").is_dir():
        found = sorted((folder / "depth").glob("*.png"), key=lambda p: natural_key(p.name))
        if found:
            return found, "tum"
    found = sorted(folder.glob("*.png"), key=lambda p: natural_key(p.name))
    return (found, "plain") if found else ([], "")


def _stem(path: Path) -> str:
    return path.name.removesuffix(".png").removesuffix(".depth")


def _load_depth(path: Path, budget: ReadBudget, stride: int) -> np.ndarray:
    """``(H, W)`` uint16 raw depth of a 16-bit PNG; its decoded size and the points its stride
    keeps are charged to ``budget`` before it is decoded."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.format != "PNG":
                raise FormatError(f"{path}: depth image is {im.format}, not PNG")
            if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise FormatError(f"{path}: depth PNG has mode {im.mode}; expected 16-bit grayscale")
            w, h = im.size
            budget.bytes_over(4 * w * h, str(path))
            budget.take_points(-(-w // stride) * -(-h // stride), str(path))
            arr = np.asarray(im)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable PNG depth image ({exc})") from exc
    if arr.ndim != 2:
        raise FormatError(f"{path}: depth image has shape {arr.shape}; expected (H, W)")
    if arr.dtype != np.uint16:
        if arr.min(initial=0) < 0 or arr.max(initial=0) > 65535:
            raise FormatError(f"{path}: depth values outside the 16-bit range")
        arr = arr.astype(np.uint16)
    return arr


def _load_color(path: Path, where: tuple[np.ndarray, np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """RGB uint8 ``(N, 3)`` of ``path`` at depth pixels ``(rows, cols)`` (scaled if sizes differ)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable colour image ({exc})") from exc
    rows, cols = where
    h, w = shape
    r = np.minimum((rows * rgb.shape[0]) // h, rgb.shape[0] - 1)
    c = np.minimum((cols * rgb.shape[1]) // w, rgb.shape[1] - 1)
    return rgb[r, c]


def _read_pose_txt(path: Path) -> np.ndarray:
    try:
        vals = [float(t) for t in path.read_text(encoding="utf-8").split()]
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise FormatError(f"{path}: not a 4 x 4 pose matrix ({exc})") from exc
    if len(vals) != 16:
        raise FormatError(f"{path}: a pose file holds 16 numbers (4 x 4), not {len(vals)}")
    return np.asarray(vals).reshape(4, 4)


def _color_files(folder: Path, depth_files: list[Path], layout: str) -> list[Path | None]:
    if layout == "7scenes":
        out: list[Path | None] = []
        for p in depth_files:
            stem = _stem(p)
            cands = [p.with_name(f"{stem}.color.{ext}") for ext in ("jpg", "png")]
            out.append(next((c for c in cands if c.is_file()), None))
        return out
    for sub in ("rgb", "color"):
        d = folder / sub
        if not d.is_dir():
            continue
        images = sorted(
            [p for p in d.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")],
            key=lambda p: natural_key(p.name),
        )
        by_stem = {p.stem: p for p in images}
        if all(_stem(p) in by_stem for p in depth_files):
            return [by_stem[_stem(p)] for p in depth_files]
        if images and all(_STAMP.match(p.stem) for p in images + depth_files):
            stamps = np.array([float(p.stem) for p in images])
            targets = np.array([float(_stem(p)) for p in depth_files])
            try:
                idx = associate(stamps, targets, max_dt=MAX_DT, name=str(d))
            except FormatError:
                return [None] * len(depth_files)
            return [images[i] for i in idx]
    return [None] * len(depth_files)


def _poses(folder: Path, depth_files: list[Path], layout: str, sel: np.ndarray) -> tuple[np.ndarray | None, str]:
    """Reference poses ``(K, 4, 4)`` of the selected frames (camera -> world) and their source."""
    if layout == "7scenes":
        pose_files = [p.with_name(f"{_stem(p)}.pose.txt") for p in depth_files]
        have = [pose_files[i].is_file() for i in sel]
        if not any(have):
            return None, ""
        if not all(have):
            missing = pose_files[sel[have.index(False)]]
            raise FormatError(f"{missing}: pose file missing (other frames have one)")
        return np.stack([_read_pose_txt(pose_files[i]) for i in sel]), "pose.txt"
    gt_file = folder / "groundtruth.txt"
    if not gt_file.is_file():
        return None, ""
    traj = read_tum(gt_file)
    assert traj.stamps is not None
    names = [_stem(p) for p in depth_files]
    if all(_STAMP.match(n) for n in names):
        targets = np.array([float(n) for n in names])
        idx = associate(traj.stamps, targets[sel], max_dt=MAX_DT, name=str(gt_file))
        return traj.poses[idx], "groundtruth.txt (time stamps)"
    if len(traj.poses) == len(depth_files):
        return traj.poses[sel], "groundtruth.txt (order)"
    raise FormatError(
        f"{gt_file}: {len(traj.poses)} poses for {len(depth_files)} depth images, and image "
        "names are not time stamps to match them by"
    )


# what a depth image says of its camera: OpenCV axes (x right, y down, z forward), so a level
# camera's vertical axis is -y in its own frame (`strep_core.profiles` turns about it)
DEPTH_CAMERA = {"kind": "depth", "axes": "opencv", "vertical_axis": [0.0, -1.0, 0.0]}


def read_depth_folder(
    path: str | Path,
    *,
    frames: str | FrameSelection | None = None,
    stride: int = 4,
    depth_scale: float = 1000.0,
    max_depth: float | None = None,
    intrinsics: Intrinsics | Seq[float] | np.ndarray | Mapping[str, float] | None = None,
    budget: ReadBudget | None = None,
) -> Sequence:
    """Read a folder of 16-bit depth PNGs as a 3D sequence in metres (camera frame).

    Args:
        path: the folder (7-Scenes or TUM RGB-D layout, see the module docstring).
        frames: ``start:stop[:step]`` over the naturally sorted images; only the selected
            images are decoded, and their positions are kept in ``Sequence.indices``.
        stride: keep every ``stride``-th pixel in rows and columns (1 keeps them all).
        depth_scale: raw units per metre (1000 for millimetres, 5000 for TUM RGB-D).
        max_depth: drop points farther than this (metres) along the optical axis.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels, a 3 x 3 K, or a mapping with those
            keys; default: read from ``camera-intrinsics.txt``, ``intrinsics.txt`` or
            ``intrinsics.json`` in the folder.
        budget: the bytes the images may decode to and the points their strides keep
            (default: the library's limits).

    Returns:
        A `Sequence` of ``(N_i, 3)`` frames (x right, y down, z forward; metres), with
        ``poses`` ``(K, 4, 4)`` camera -> world when reference poses are there, and
        ``colors`` ``(N_i, 3)`` uint8 when every selected frame has a colour image.

    Raises:
        FormatError: no depth images, missing or malformed intrinsics, an image that is
            not a 16-bit PNG, malformed or unmatched poses.
        SequenceError: too few frames or valid pixels, non-finite poses.
    """
    path = Path(path)
    if not path.is_dir():
        raise FormatError(f"{path}: not a folder of depth images")
    if stride < 1:
        raise FormatError(f"{path}: stride must be at least 1, not {stride}")
    if not depth_scale > 0:
        raise FormatError(f"{path}: depth_scale must be positive, not {depth_scale}")
    files, layout = find_depth_images(path)
    if not files:
        raise FormatError(f"{path}: no depth images (*.depth.png, depth/*.png or *.png)")
    if intrinsics is None:
        found = next((path / n for n in INTRINSICS_FILES if (path / n).is_file()), None)
        if found is None:
            raise FormatError(f"{path}: no intrinsics file ({', '.join(INTRINSICS_FILES)}); pass intrinsics")
        fx, fy, cx, cy = read_intrinsics(found)
    else:
        fx, fy, cx, cy = _as_intrinsics(intrinsics, f"{path}: intrinsics argument")

    sel = FrameSelection.parse(frames).keep(len(files))
    poses, pose_source = _poses(path, files, layout, sel)
    color_files = _color_files(path, files, layout)
    use_color = all(color_files[i] is not None for i in sel)

    budget = budget or ReadBudget()
    pts, cols = [], []
    for i in sel:
        raw = _load_depth(files[i], budget, stride)
        h, w = raw.shape
        rows, cols_ = np.mgrid[0:h:stride, 0:w:stride]
        d = raw[rows, cols_]
        ok = (d > 0) & (d != INVALID_DEPTH)
        z = d[ok].astype(np.float64) / depth_scale
        r, c = rows[ok], cols_[ok]
        if max_depth is not None:
            keep = z <= max_depth
            z, r, c = z[keep], r[keep], c[keep]
        pts.append(np.stack([(c - cx) * z / fx, (r - cy) * z / fy, z], 1))
        if use_color:
            color_file = color_files[i]
            assert color_file is not None
            cols.append(_load_color(color_file, (r, c), (h, w)))
    try:
        return Sequence(
            frames=pts,
            name=path.name,
            unit="m",
            poses=poses,
            indices=sel,
            colors=cols if use_color else None,
            meta={
                "source": str(path),
                "format": "depth",
                "layout": layout,
                "stride": stride,
                "depth_scale": depth_scale,
                "max_depth": max_depth,
                "intrinsics": [fx, fy, cx, cy],
                "sensor": DEPTH_CAMERA,
                "poses_from": pose_source or None,
                "files": [files[i].name for i in sel],
            },
        )
    except SequenceError as exc:
        raise SequenceError(f"{path}: {exc}") from exc
