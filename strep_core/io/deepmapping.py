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
from strep_core.io.pcd import parse_pcd
from strep_core.sequence import FrameSelection, Sequence

SCALE = 512.0  # DeepMapping stores local points in pixels / 512
_FRAME = re.compile(r"(?:^|/)(\d+)\.pcd$")


def _read_members(path: Path) -> tuple[dict[int, bytes], bytes | None]:
    frames: dict[int, bytes] = {}
    mat: bytes | None = None
    if path.is_dir():
        for p in sorted(path.rglob("*")):
            if m := _FRAME.search(p.as_posix()):
                frames[int(m.group(1))] = p.read_bytes()
            elif p.name == "gt_pose.mat":
                mat = p.read_bytes()
        return frames, mat
    try:
        with tarfile.open(path) as tar:
            for member in tar:
                if not member.isfile():
                    continue
                fobj = tar.extractfile(member)
                if fobj is None:
                    continue
                if m := _FRAME.search(member.name):
                    frames[int(m.group(1))] = fobj.read()
                elif member.name.rsplit("/", 1)[-1] == "gt_pose.mat":
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


def read_deepmapping(path: str | Path, *, frames: str | FrameSelection | None = None) -> Sequence:
    """Read a DeepMapping 2D sequence from a folder or ``.tar``.

    Returns a 2D `Sequence` in map pixels with ground truth from ``gt_pose.mat`` if present.
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(f"{path}: no such file or folder")
    members, mat = _read_members(path)
    if not members:
        raise FormatError(f"{path}: no NNN.pcd frames found (DeepMapping format)")
    order = sorted(members)
    if order != list(range(order[0], order[0] + len(order))):
        raise FormatError(f"{path}: frame numbers are not contiguous ({order[0]}..{order[-1]})")
    sel = FrameSelection.parse(frames).indices(len(order))
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
        meta={"source": str(path), "format": "deepmapping"},
    )
