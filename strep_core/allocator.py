"""Freed memory kept for reuse: glibc's allocator told to keep numpy's large temporaries.

By default glibc serves an allocation above 128 KiB (a threshold it raises to at most 32 MiB as
such blocks are freed) with a fresh ``mmap`` and gives the heap's free top back to the system
past twice that. Every score batch, padded grid and index array of the branch and bound is
such a block, so each one is faulted in page by page again. On this project's machines a
fault is dear: one batch of 5,000 nodes x 200 points scores in 7.8 ms with fresh memory and
in 1.9 ms with reused memory, and freiburg-079[0:600] registers in 18.2 s against 21.8 s.
Poses are unchanged to the last bit; the peak grows by about a tenth
(docs/design/laser-slam.md, round 12).

`keep_freed_memory` serves blocks up to `MMAP_MIB` from the heap and keeps up to `TRIM_MIB` of
its free top. It is process-wide, set once, and does nothing where the C library has no
``mallopt`` (macOS) or ignores it (musl).
"""

from __future__ import annotations

import ctypes
import functools

M_TRIM_THRESHOLD = -1  # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_MIB = 64  # blocks above this still come from (and go back with) mmap
TRIM_MIB = 256  # at most this much free heap top stays resident


@functools.cache
def keep_freed_memory() -> bool:
    """Tune the process's allocator (once); True where glibc took both settings."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    took_mmap = mallopt(M_MMAP_THRESHOLD, MMAP_MIB << 20)  # both are set, whatever the first answers
    took_trim = mallopt(M_TRIM_THRESHOLD, TRIM_MIB << 20)
    return bool(took_mmap and took_trim)
