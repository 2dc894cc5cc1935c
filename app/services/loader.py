"""Reading a job's sequence in the service process, for the viewer and comparison recordings.

Workers read their input in their own process. The live viewer and the comparison
recordings also need the `Sequence` (its frames and ground truth): `SequenceLoader` reads it
once per request on the caller's thread (never the supervisor's), with the frame selections
of the upload and of the run applied, exactly as the job's worker does.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future

from app.services.sequences import SequenceService
from app.services.worker import load_source
from strep_core.sequence import Sequence


class SequenceGone(LookupError):
    """The sequence of a job no longer exists (deleted after the job ran)."""


class SequenceLoader:
    """Loads the sequence a job registers. Thread-safe.

    Concurrent requests for the same input share one read (the jobs of a comparison start
    together), and the last sequence read is kept for ``keep_seconds`` so the comparison's
    recording, written right after its last job, does not read it again.
    """

    def __init__(
        self,
        sequences: SequenceService,
        max_extract_bytes: int,
        *,
        max_points: int | None = None,
        keep_seconds: float = 60.0,
    ) -> None:
        self.sequences = sequences
        self.max_extract_bytes = max_extract_bytes
        self.max_points = max_points
        self.keep_seconds = keep_seconds
        self.reads = 0  # inputs actually read (for tests)
        self._lock = threading.Lock()
        self._inflight: dict[tuple[str, str | None], Future[Sequence]] = {}
        self._last: tuple[tuple[str, str | None], Sequence, float] | None = None

    def load(self, sequence_id: str, frames: str | None = None) -> Sequence:
        """The sequence ``sequence_id`` with the run's frame selection ``frames`` applied.

        Blocks while reading. Raises `SequenceGone`, or the reader's `StrepError`.
        """
        key = (sequence_id, frames or None)
        with self._lock:
            self._expire()
            if self._last is not None and self._last[0] == key:
                self._last = (key, self._last[1], time.monotonic())
                return self._last[1]
            future = self._inflight.get(key)
            owner = future is None
            if future is None:
                future = self._inflight[key] = Future()
        if not owner:
            return future.result()
        try:
            seq = self._read(sequence_id, frames)
        except BaseException as exc:
            future.set_exception(exc)
            with self._lock:
                self._inflight.pop(key, None)
            raise
        future.set_result(seq)
        with self._lock:
            self._inflight.pop(key, None)
            self._last = (key, seq, time.monotonic())
        return seq

    def expire(self) -> None:
        """Forget the kept sequence once ``keep_seconds`` have passed since its last use."""
        with self._lock:
            self._expire()

    def clear(self) -> None:
        with self._lock:
            self._last = None

    def _expire(self) -> None:
        if self._last is not None and time.monotonic() - self._last[2] > self.keep_seconds:
            self._last = None

    def _read(self, sequence_id: str, frames: str | None) -> Sequence:
        source = self.sequences.source_of(sequence_id)
        if source is None:
            raise SequenceGone(f"its sequence {sequence_id!r} no longer exists")
        path, selection = source
        extract_dir = str(self.sequences.extract_dir / "service")
        seq: Sequence = load_source(path, selection, self.max_extract_bytes, extract_dir, self.max_points)
        seq.name = self.sequences.name_of(sequence_id) or seq.name  # an upload: its name, not "sequence"
        self.reads += 1
        return seq.select(frames) if frames else seq
