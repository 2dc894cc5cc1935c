"""One budget per read of a sequence: bytes inflated and points read.

Every reader that inflates or unpacks (``.zip``, ``.npz``, gzip, bzip2 and xz streams, ``.tar``)
or builds points charges one `ReadBudget` *while* it reads, chunk by chunk, so that a small
file that would inflate to gigabytes is refused after at most ``max_inflated_bytes`` bytes of
work and memory, whatever sizes it declares. Counted:

* **bytes inflated**: every byte that comes out of a decompressor or an archive (a ``.zip``
  member extracted, an ``.npz`` array, the stream of a ``.tar`` -- compressed or not -- and a
  gzipped CARMEN log); declared sizes (an ``.npz`` array's header, a ``.zip`` directory) are
  checked first so that nothing is allocated past the budget;
* **points read**: every point (or range reading) a reader builds, before any frame
  selection; headers that declare a count (``.npz`` arrays, PCD and PLY files) are checked
  before the points are read.

A reader given a budget that runs out raises `FormatError` with the limit in its message and
leaves nothing behind (extractions are in temporary folders). `load_sequence` makes one
budget per call; the service passes its settings (``STREP_MAX_INFLATED_BYTES``,
``STREP_MAX_POINTS``), the library and the CLI use the generous defaults below.
"""

from __future__ import annotations

import bz2
import gzip
import io
import lzma
import re
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from strep_core.errors import FormatError

__all__ = [
    "CHUNK",
    "DEFAULT_MAX_INFLATED_BYTES",
    "DEFAULT_MAX_POINTS",
    "CountingReader",
    "ReadBudget",
    "declared_cloud_points",
    "open_decompressed",
]

DEFAULT_MAX_INFLATED_BYTES = 8 * 1024**3  # 8 GiB: the library's and the CLI's default
DEFAULT_MAX_POINTS = 250_000_000  # the library's and the CLI's default
CHUNK = 1 << 20  # bytes read at a time while inflating
BUFFER = 64 * 1024  # read-ahead of a streamed reader: charged before its bytes are used

_OPENERS: dict[str, Callable[..., Any]] = {"gzip": gzip.open, "bzip2": bz2.open, "xz": lzma.open}
_MAGIC: tuple[tuple[bytes, str], ...] = ((b"\x1f\x8b", "gzip"), (b"BZh", "bzip2"), (b"\xfd7zXZ\x00", "xz"))


class ReadBudget:
    """What one read may still inflate and build; raises `FormatError` once it is spent.

    Not thread-safe: one budget per read.
    """

    def __init__(self, max_inflated_bytes: int | None = None, max_points: int | None = None) -> None:
        self.max_inflated_bytes = DEFAULT_MAX_INFLATED_BYTES if max_inflated_bytes is None else int(max_inflated_bytes)
        self.max_points = DEFAULT_MAX_POINTS if max_points is None else int(max_points)
        self.inflated = 0
        self.points = 0

    def bytes_over(self, count: int, where: str, *, declared: bool = False) -> None:
        """Charge ``count`` bytes inflated (or check them, ``declared``: a size a header gives)."""
        total = self.inflated + int(count)
        if total > self.max_inflated_bytes:
            how = "declares" if declared else "inflates to"
            raise FormatError(
                f"{where}: {how} more than the limit of {self.max_inflated_bytes} bytes "
                "(the most one sequence may inflate to)"
            )
        if not declared:
            self.inflated = total

    def take_points(self, count: int, where: str, *, declared: bool = False) -> None:
        """Charge ``count`` points read (or check them, ``declared``: a count a header gives)."""
        total = self.points + int(count)
        if total > self.max_points:
            how = "declares" if declared else "holds"
            raise FormatError(
                f"{where}: {how} more than the limit of {self.max_points} points "
                f"(the most one sequence may hold; {total} with the frames before)"
            )
        if not declared:
            self.points = total

    def read_all(self, fobj: IO[bytes], where: str) -> bytes:
        """All of ``fobj``, read in chunks and charged as they come."""
        parts = []
        while chunk := fobj.read(CHUNK):
            self.bytes_over(len(chunk), where)
            parts.append(chunk)
        return b"".join(parts)


class CountingReader(io.RawIOBase):
    """A read-only stream over ``raw`` that charges a budget for every byte read through it."""

    def __init__(self, raw: IO[bytes], budget: ReadBudget, where: str) -> None:
        super().__init__()
        self.raw = raw
        self.budget = budget
        self.where = where

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        data = self.raw.read(min(len(buffer), CHUNK))
        self.budget.bytes_over(len(data), self.where)
        buffer[: len(data)] = data
        return len(data)

    def close(self) -> None:
        self.raw.close()
        super().close()


def compression_of(path: Path) -> str | None:
    """``gzip``, ``bzip2`` or ``xz`` from the file's first bytes (whatever its name); None: plain."""
    with open(path, "rb") as f:
        head = f.read(6)
    return next((name for magic, name in _MAGIC if head.startswith(magic)), None)


def open_decompressed(path: Path, budget: ReadBudget) -> IO[bytes]:
    """``path`` opened for streaming, decompressed when its first bytes say so, every byte that
    comes out charged to ``budget``. The caller closes it."""
    kind = compression_of(path)
    raw: IO[bytes] = _OPENERS[kind](path, "rb") if kind else open(path, "rb")  # noqa: SIM115 - closed with the reader
    return io.BufferedReader(CountingReader(raw, budget, str(path)), BUFFER)


_PCD_POINTS = re.compile(rb"^\s*POINTS\s+(\d+)", re.MULTILINE)
_PLY_VERTICES = re.compile(rb"^\s*element\s+vertex\s+(\d+)", re.MULTILINE)


def declared_cloud_points(head: bytes) -> int | None:
    """The point count a PCD (``POINTS n``) or PLY (``element vertex n``) header declares, from
    the file's first bytes; None when there is none."""
    if head.startswith(b"ply"):
        match = _PLY_VERTICES.search(head.split(b"end_header", 1)[0])
    else:
        match = _PCD_POINTS.search(head.split(b"\nDATA", 1)[0])
    if match is None:
        return None
    digits = match.group(1)
    return int(digits) if len(digits) <= 18 else 10**18  # int() of a longer string may raise
