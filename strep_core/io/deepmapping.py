"""DeepMapping's 2D format: ``NNN.pcd`` frames plus ``gt_pose.mat``, in a folder or a ``.tar``.

Points are stored in map pixels divided by 512 (see the shared data README); they are
scaled back to pixels here so that ATE comes out in pixels as in DeepMapping's papers:
``global_px = R(theta) (p * 512) + (x, y)``.
"""

from __future__ import annotations

import io
import re
import tarfile
from pathlib import Path

import numpy as np

from strep_core import geometry as g
from strep_core.errors import FormatError
from strep_core.io.limits import ReadBudget, declared_cloud_points, open_decompressed
from strep_core.io.pcd import parse_pcd
from strep_core.sequence import FrameSelection, Sequence

SCALE = 512.0  # DeepMapping stores local points in pixels / 512
HEAD_BYTES = 64 * 1024  # a PCD header is a few hundred bytes
_FRAME = re.compile(r"(?:^|/)(\d+)\.pcd$")


def _charge_frame(data: bytes, budget: ReadBudget, where: str) -> bytes:
    """A frame's bytes, once the points its PCD header declares are charged (parse_pcd reads
    exactly that many)."""
    declared = declared_cloud_points(data[:HEAD_BYTES])
    if declared is not None:
        budget.take_points(declared, where)
    return data


def _read_members(path: Path, budget: ReadBudget) -> tuple[dict[int, bytes], bytes | None]:
    """The frames' and ``gt_pose.mat``'s bytes. A ``.tar`` (compressed or not, whatever its
    name says) is streamed once, every byte coming out of it charged to ``budget``."""
    frames: dict[int, bytes] = {}
    mat: bytes | None = None
    if path.is_dir():
        for p in sorted(path.rglob("*")):
            if m := _FRAME.search(p.as_posix()):
                frames[int(m.group(1))] = _charge_frame(p.read_bytes(), budget, str(p))
            elif p.name == "gt_pose.mat":
                mat = p.read_bytes()
        return frames, mat
    try:
        with open_decompressed(path, budget) as stream, tarfile.open(fileobj=stream, mode="r|") as tar:
            for member in tar:
                if member.issparse():
                    raise FormatError(f"{path}: entry {member.name!r} is a sparse file (not supported)")
                frame = _FRAME.search(member.name)
                if not member.isfile() or not (frame or member.name.rsplit("/", 1)[-1] == "gt_pose.mat"):
                    continue
                fobj = tar.extractfile(member)
                if fobj is None:
                    continue
                where = f"{path}:{member.name}"
                budget.bytes_over(member.size, where, declared=True)
                if frame:  # the header's point count is checked before the rest is read
                    head = _charge_frame(fobj.read(HEAD_BYTES), budget, where)
                    frames[int(frame.group(1))] = head + fobj.read()
                else:
                    mat = fobj.read()
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise FormatError(f"{path}: not a readable tar archive ({exc})") from exc
    return frames, mat


def _read_gt(mat: bytes, name: str) -> np.ndarray:
    from scipy.io import loadmat

    try:
        content = loadmat(io.BytesIO(mat))
    except Exception as exc:  # scipy raises many kinds on garbage
        raise FormatError(f"{name}: gt_pose.mat is not a readable MATLAB file ({exc})") from exc
    arrays = [v for k, v in content.items() if not k.startswith("__") and isinstance(v, np.ndarray)]
    arrays = [a for a in arrays if a.ndim == 2 and a.shape[1] == 3]
    if not arrays:
        raise FormatError(f"{name}: gt_pose.mat holds no (K, 3) pose array")
    return np.asarray(arrays[0], dtype=np.float64)


def read_deepmapping(
    path: str | Path, *, frames: str | FrameSelection | None = None, budget: ReadBudget | None = None
) -> Sequence:
    """Read a DeepMapping 2D sequence from a folder or ``.tar`` (plain, gzip, bzip2 or xz)
    within ``budget`` (default: the library's limits).

    Returns a 2D `Sequence` in map pixels with ground truth from ``gt_pose.mat`` if present.
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(f"{path}: no such file or folder")
    members, mat = _read_members(path, budget or ReadBudget())
    if not members:
        raise FormatError(f"{path}: no NNN.pcd frames found (DeepMapping format)")
    order = sorted(members)
    if order != list(range(order[0], order[0] + len(order))):
        raise FormatError(f"{path}: frame numbers are not contiguous ({order[0]}..{order[-1]})")
    sel = FrameSelection.parse(frames).keep(len(order))
    pts = []
    for i in sel:
        xyz = parse_pcd(members[order[i]], name=f"{path}:{order[i]:03d}.pcd")
        pts.append(xyz[:, :2] * SCALE)
    poses = None
    if mat is not None:
        gt = _read_gt(mat, str(path))
        if len(gt) != len(order):
            raise FormatError(f"{path}: gt_pose.mat has {len(gt)} poses for {len(order)} frames")
        poses = g.se2_from_xytheta(gt[sel])
    return Sequence(
        frames=pts,
        name=path.name.removesuffix(".tar"),
        unit="px",
        poses=poses,
        indices=sel,
        meta={"source": str(path), "format": "deepmapping", "sensor": {"kind": "laser", "planar": True}},
    )
