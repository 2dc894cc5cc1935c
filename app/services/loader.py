"""The scene of a job, for the live viewer and the comparison recordings.

The API process never parses an uploaded input: a job's worker writes the frames it registers
to the job's ``scene.npz`` (`app.services.scenes`) before its method starts, and
`SequenceLoader` reads that file, on the caller's thread (never the supervisor's).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

from app.services.scenes import read_scene
from strep_core.sequence import Sequence


class SequenceGone(LookupError):
    """The job has no scene: it failed before its frames were read, or its files are gone."""


class SequenceLoader:
    """Reads the scene of a job. Thread-safe.

    The last scene read is kept for ``keep_seconds``, so the comparison's recording, written
    right after its last job, and the viewer's reopening of a run do not read it again.
    """

    def __init__(self, scene_path: Callable[[str], Path], *, keep_seconds: float = 60.0) -> None:
        self.scene_path = scene_path
        self.keep_seconds = keep_seconds
        self.reads = 0  # scene files actually read (for tests)
        self._lock = threading.Lock()
        self._last: tuple[str, Sequence, float] | None = None

    def load(self, job_id: str) -> Sequence:
        """The frames job ``job_id`` registers. Blocks while reading; raises `SequenceGone`."""
        with self._lock:
            self._expire()
            if self._last is not None and self._last[0] == job_id:
                self._last = (job_id, self._last[1], time.monotonic())
                return self._last[1]
        path = self.scene_path(job_id)
        try:
            seq = read_scene(path)
        except FileNotFoundError:
            raise SequenceGone(f"job {job_id!r} has no scene: it ended before its input was read") from None
        with self._lock:
            self.reads += 1
            self._last = (job_id, seq, time.monotonic())
        return seq

    def expire(self) -> None:
        """Forget the kept scene once ``keep_seconds`` have passed since its last use."""
        with self._lock:
            self._expire()

    def clear(self) -> None:
        with self._lock:
            self._last = None

    def _expire(self) -> None:
        if self._last is not None and time.monotonic() - self._last[2] > self.keep_seconds:
            self._last = None
