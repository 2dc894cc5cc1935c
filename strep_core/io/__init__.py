"""Readers and writers. `load_sequence` picks a reader from the path.

* ``*.npz`` -> `read_npz`
* ``*.tar``, or a folder of ``NNN.pcd`` + ``gt_pose.mat`` -> `read_deepmapping`
* ``*.log``, ``*.log.gz`` -> `read_carmen`
* ``*.conf``, or a folder holding one -> `read_conf`
* a folder of ``*.depth.png`` or ``depth/*.png`` -> `read_depth_folder`
* a folder of ``*.ply`` / ``*.pcd`` / Velodyne ``*.bin`` -> `read_folder`
* ``*.zip`` of any of the above -> extracted safely (`extract_zip`), then dispatched

Each call of `load_sequence` reads within one `ReadBudget` (`strep_core.io.limits`): the bytes
inflated by every container and compressed stream it opens, and the points its readers
build, are charged while they are read; past the budget the read stops with `FormatError`.

`FORMATS` is the one table of formats: detection, dispatch, the CLI's and the docs' list and
the service's accepted uploads all read it, so a new format is its reader module plus one row
here (`docs/design/extending.md`). Open3D is imported only by the readers that need it
(``folder``, ``conf``); ``sample:NAME`` sources are resolved by `strep_core.samples` before
`load_sequence` is called.
"""

from __future__ import annotations

import inspect
import os
import stat
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any, NamedTuple

from strep_core.errors import ConfigError, FormatError, StrepError
from strep_core.io.carmen import read_carmen
from strep_core.io.deepmapping import read_deepmapping
from strep_core.io.depth import read_depth_folder, read_intrinsics
from strep_core.io.folder import read_conf, read_folder
from strep_core.io.limits import DEFAULT_MAX_INFLATED_BYTES, DEFAULT_MAX_POINTS, ReadBudget
from strep_core.io.npz import read_npz, write_npz
from strep_core.io.poses import read_kitti, read_poses, read_tum
from strep_core.io.writers import write_json, write_ply, write_tum
from strep_core.sequence import FrameSelection, Sequence

__all__ = [
    "DEFAULT_MAX_EXTRACT_BYTES",
    "DEFAULT_MAX_POINTS",
    "FORMATS",
    "FormatInfo",
    "ReadBudget",
    "detect_format",
    "extract_zip",
    "load_sequence",
    "read_carmen",
    "read_conf",
    "read_deepmapping",
    "read_depth_folder",
    "read_folder",
    "read_intrinsics",
    "read_kitti",
    "read_npz",
    "read_poses",
    "read_tum",
    "write_json",
    "write_npz",
    "write_ply",
    "write_tum",
]

DEFAULT_MAX_EXTRACT_BYTES = DEFAULT_MAX_INFLATED_BYTES  # the most one read may inflate to


def _is_deepmapping_folder(folder: Path) -> bool:
    if not (folder / "gt_pose.mat").is_file():
        return False
    return any(p.stem.isdigit() for p in folder.glob("*.pcd"))


def _is_conf_folder(folder: Path) -> bool:
    return any(folder.glob("*.conf"))


def _is_depth_folder(folder: Path) -> bool:
    return any(folder.glob("*.depth.png")) or any((folder / "depth").glob("*.png"))


def _is_cloud_folder(folder: Path) -> bool:
    return any(p.suffix.lower() in (".ply", ".pcd", ".bin") for p in folder.iterdir())


class FormatInfo(NamedTuple):
    """One input format: how it is recognised, what reads it, and how it is described."""

    name: str
    extensions: tuple[str, ...]  # for people: the suffixes of the file, or of the files in the folder
    description: str
    reader: Callable[..., Sequence] | None = None  # None: a container, extracted and dispatched again
    files: tuple[str, ...] = ()  # a file whose lower-case name ends so is in this format
    folder: Callable[[Path], bool] | None = None  # a folder for which this is true is in this format
    one_file: bool = False  # the whole sequence is in one file: what the service accepts as an upload


# Checked in this order: the first match wins (a folder with gt_pose.mat is DeepMapping's, not PCD frames).
FORMATS: tuple[FormatInfo, ...] = (
    FormatInfo(
        "npz",
        (".npz",),
        "numpy archive: points + counts (or frames), optional poses, unit",
        read_npz,
        files=(".npz",),
        one_file=True,
    ),
    FormatInfo(
        "deepmapping",
        (".tar",),
        "DeepMapping 2D: NNN.pcd frames + gt_pose.mat, in a .tar or a folder (map pixels)",
        read_deepmapping,
        files=(".tar",),
        folder=_is_deepmapping_folder,
        one_file=True,
    ),
    FormatInfo(
        "carmen",
        (".log", ".log.gz"),
        "CARMEN laser log: FLASER scans, corrected poses (metres)",
        read_carmen,
        files=(".log", ".log.gz"),
        one_file=True,
    ),
    FormatInfo(
        "conf",
        (".conf",),
        "Stanford range scans: PLY files + a .conf of bmesh poses",
        read_conf,
        files=(".conf",),
        folder=_is_conf_folder,
    ),
    FormatInfo(
        "depth",
        (".depth.png", ".png"),
        "folder of 16-bit depth PNGs (7-Scenes or TUM RGB-D layout) + intrinsics, optional poses",
        read_depth_folder,
        folder=_is_depth_folder,
    ),
    FormatInfo(
        "folder",
        (".ply", ".pcd", ".bin"),
        "folder of PLY/PCD frames (every per-point field kept) or Velodyne .bin scans, optional TUM or KITTI pose file",
        read_folder,
        folder=_is_cloud_folder,
    ),
    FormatInfo("zip", (".zip",), "a .zip holding any of the formats above", files=(".zip",), one_file=True),
)


def _expected() -> str:
    return ", ".join(f"{f.name} ({' '.join(f.extensions)})" for f in FORMATS)


def detect_format(source: str | Path) -> str:
    """Name of the format of ``source`` (a key of `FORMATS`), from its name and content.

    Raises:
        FormatError: missing input, or a format none of the readers knows.
    """
    path = Path(source)
    name = path.name.lower()
    if not path.exists():
        raise FormatError(f"{path}: no such file or folder; expected one of {_expected()}")
    if path.is_file():
        for f in FORMATS:
            if name.endswith(f.files):
                return f.name
    elif path.is_dir():
        for f in FORMATS:
            if f.folder is not None and f.folder(path):
                return f.name
    raise FormatError(f"{path}: unknown format; expected one of {_expected()}")


def _check_member(info: zipfile.ZipInfo, archive: Path) -> PurePosixPath:
    name = info.filename.replace("\\", "/")
    rel = PurePosixPath(name)
    if name.startswith("/") or (len(name) > 1 and name[1] == ":") or ".." in rel.parts:
        raise FormatError(f"{archive}: unsafe entry {info.filename!r} (absolute or '..' path)")
    mode = info.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise FormatError(f"{archive}: entry {info.filename!r} is a symbolic link")
    return rel


def extract_zip(
    archive: str | Path,
    dest: str | Path,
    *,
    max_bytes: int = DEFAULT_MAX_EXTRACT_BYTES,
    budget: ReadBudget | None = None,
) -> Path:
    """Extract ``archive`` into the folder ``dest`` safely.

    Entries with absolute paths, ``..`` components or symbolic links are refused, and the
    extraction stops once more than ``max_bytes`` bytes (or what ``budget`` has left) have
    been written, whatever sizes the archive declares. Returns ``dest``.

    Raises:
        FormatError: not a zip file, an unsafe entry, or too much data.
    """
    archive, dest = Path(archive), Path(dest)
    budget = budget or ReadBudget(max_inflated_bytes=max_bytes)
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        raise FormatError(f"{archive}: not a readable zip archive ({exc})") from exc
    with zf:
        infos = zf.infolist()
        members = [(info, _check_member(info, archive)) for info in infos]
        declared = sum(info.file_size for info in infos)
        if budget.inflated + declared > budget.max_inflated_bytes:
            raise FormatError(f"{archive}: inflates to {declared} bytes, over the limit of {budget.max_inflated_bytes}")
        for info, rel in members:
            target = dest.joinpath(*rel.parts)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                with zf.open(info) as src, open(target, "wb") as out:
                    while chunk := src.read(1 << 20):
                        budget.bytes_over(len(chunk), str(archive))
                        out.write(chunk)
            except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError) as exc:
                raise FormatError(f"{archive}: cannot extract {info.filename!r} ({exc})") from exc
    return dest


def _content_root(folder: Path) -> Path:
    """What an extracted archive holds: descend through single wrapping folders down to a
    folder with several entries, or to a single file."""
    while True:
        entries = [p for p in folder.iterdir() if p.name not in ("__MACOSX", ".DS_Store")]
        if len(entries) != 1:
            return folder
        if entries[0].is_file() or entries[0].name == "depth":  # depth/*.png: the folder holding it is the content
            return entries[0] if entries[0].is_file() else folder
        folder = entries[0]


def load_sequence(
    source: str | Path,
    *,
    frames: str | FrameSelection | None = None,
    max_extract_bytes: int = DEFAULT_MAX_EXTRACT_BYTES,
    max_points: int = DEFAULT_MAX_POINTS,
    extract_dir: str | Path | None = None,
    **options: Any,
) -> Sequence:
    """Read a sequence from any supported input (see `FORMATS`), dispatching on the path.

    Args:
        source: a file or folder; a ``.zip`` is extracted to a temporary folder (removed
            afterwards) and its content dispatched in turn.
        frames: ``start:stop[:step]``; original indices are kept in ``Sequence.indices``.
        max_extract_bytes: the most the read may inflate, all containers and compressed
            streams together (``.zip``, ``.npz``, gzip, ``.tar``; default 8 GiB).
        max_points: the most points the read may build, before any frame selection
            (default 250 million).
        extract_dir: the folder (existing) in which a ``.zip`` is extracted, in a ``strep-zip-*``
            folder of its own; None: the system's temporary folder. A service gives one that it
            sweeps at start-up, so a reader killed mid-extraction leaves nothing for good.
        **options: passed to the reader (e.g. ``max_range`` for CARMEN, ``stride`` for depth).

    Raises:
        FormatError: missing input, unknown format, or a malformed file.
        ConfigError: an option the format's reader does not take.
        SequenceError: the content is not a valid sequence (NaN, too few frames or points).
    """
    path = Path(source)
    fmt = detect_format(path)
    budget = ReadBudget(max_inflated_bytes=max_extract_bytes, max_points=max_points)
    if fmt == "zip":
        with tempfile.TemporaryDirectory(prefix="strep-zip-", dir=extract_dir) as tmp:
            extract_zip(path, tmp, budget=budget)
            inner = _content_root(Path(tmp))
            if inner.is_file() and inner.name.lower().endswith(".zip"):
                raise FormatError(f"{path}: a zip inside a zip is not supported")
            try:
                inner_fmt = detect_format(inner)
            except FormatError as exc:
                raise FormatError(
                    f"{path}: the archive's content has an unknown format; expected one of {_expected()}"
                ) from exc
            try:
                seq = _read(inner_fmt, inner, frames, options, budget)
            except StrepError as exc:  # name the archive, not the temporary folder
                text = str(exc).replace(f"{tmp}{os.sep}", f"{path}:").replace(tmp, str(path))
                raise type(exc)(text) from exc
            seq.meta = {**seq.meta, "source": str(path), "archive_member": str(inner.relative_to(tmp))}
            return seq
    return _read(fmt, path, frames, options, budget)


def _read(
    fmt: str, path: Path, frames: str | FrameSelection | None, options: dict[str, Any], budget: ReadBudget
) -> Sequence:
    reader = next(f.reader for f in FORMATS if f.name == fmt and f.reader is not None)
    accepted = set(inspect.signature(reader).parameters) - {"path", "frames", "budget"}
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise ConfigError(
            f"{path}: option(s) {', '.join(unknown)} do not apply to the {fmt} format "
            f"(it takes: {', '.join(sorted(accepted)) or 'none'})"
        )
    seq = reader(path, frames=frames, budget=budget, **options)
    if seq.num_points > budget.max_points:  # every reader charges as it reads; this is the backstop
        raise FormatError(f"{path}: holds {seq.num_points} points, over the limit of {budget.max_points}")
    return seq
