"""One Rerun recording per comparison: all its methods side by side, built from stored events.

Every job's worker records its own ``recording.rrd``. A comparison's recording is written
by the service when the comparison's last job has finished: `ComparisonRecordings` listens
to the event stream (`Broadcaster.listen`), and on a job's final status checks, on its own
thread, whether the job's comparison is complete; if so it reads the sequence and the jobs'
stored events and writes ``results/<comparison id>/recording.rrd`` with
`app.rrd.write_recording` (to a temporary name, renamed into place). Nothing of this
runs on the supervisor thread or on the event loop.

A comparison whose recording is missing (it finished before this existed, or the service
stopped while writing it) gets it on request: `ensure`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Literal

from app.core.config import Settings
from app.services.loader import SequenceLoader
from app.store import ACTIVE_STATUSES, Store, StoredEvent
from strep_core.events import PROGRESS_KINDS

log = logging.getLogger("strep.service")

RECORDING = "recording.rrd"
PAGE = 1000

RecordingState = Literal["ready", "pending", "failed", "missing"]


class NothingRecorded(RuntimeError):
    """No job of the comparison reported any progress (all failed or were cancelled early)."""


class ComparisonRecordings:
    """Writes and finds comparison recordings; see the module docstring. Thread-safe."""

    def __init__(self, settings: Settings, store: Store, loader: SequenceLoader) -> None:
        self.settings = settings
        self.store = store
        self.loader = loader
        self.written = 0  # recordings written (for tests)
        self._lock = threading.Lock()
        self._pending: set[str] = set()
        self._errors: dict[str, str] = {}
        self._closed = False
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="strep-cmp-recording")

    def path(self, comparison_id: str) -> Path:
        return self.settings.results_dir / comparison_id / RECORDING

    def state(self, comparison_id: str) -> tuple[RecordingState, str | None]:
        """``ready`` (the file exists), ``pending`` (being written), ``failed`` (with the reason)
        or ``missing``."""
        with self._lock:
            if comparison_id in self._pending:
                return "pending", None
            if comparison_id in self._errors:
                return "failed", self._errors[comparison_id]
        return ("ready", None) if self.path(comparison_id).is_file() else ("missing", None)

    # ---- triggers ------------------------------------------------------------------------------
    def on_events(self, events: Iterable[StoredEvent]) -> None:
        """`Broadcaster` listener: queue a check for each job that reached a final status."""
        for ev in events:
            if ev.kind == "status" and ev.final_status:
                self._submit(self._job_finished, ev.job_id)

    def ensure(self, comparison_id: str) -> None:
        """Write the recording of a finished comparison if it is missing (returns at once)."""
        if self.state(comparison_id)[0] == "missing":
            self._request(comparison_id)

    def close(self) -> None:
        """Stop: a recording being written is finished, queued ones are dropped."""
        with self._lock:
            self._closed = True
        self._executor.shutdown(wait=True, cancel_futures=True)

    # ---- the writer thread ---------------------------------------------------------------------
    def _submit(self, fn: Callable[[str], None], arg: str) -> None:
        with self._lock:
            if self._closed:
                return
            self._executor.submit(fn, arg)

    def _job_finished(self, job_id: str) -> None:
        job = self.store.get_job(job_id)
        if job is None or not job["comparison_id"]:
            return
        comparison_id = job["comparison_id"]
        rows, _ = self.store.list_jobs(comparison_id=comparison_id, limit=1000, newest_first=False)
        if any(r["status"] in ACTIVE_STATUSES for r in rows):
            return
        if not self.path(comparison_id).is_file():
            self._request(comparison_id)

    def _request(self, comparison_id: str) -> None:
        with self._lock:
            if comparison_id in self._pending or self._closed:
                return
            self._pending.add(comparison_id)
            self._errors.pop(comparison_id, None)
            self._executor.submit(self._build, comparison_id)

    def _build(self, comparison_id: str) -> None:
        try:
            if not self.path(comparison_id).is_file():
                self.write(comparison_id)
        except Exception as exc:
            reason = str(exc) or type(exc).__name__
            if not isinstance(exc, (NothingRecorded, LookupError)):
                log.exception("the recording of comparison %s failed", comparison_id)
            with self._lock:
                self._errors[comparison_id] = reason
        finally:
            with self._lock:
                self._pending.discard(comparison_id)

    def write(self, comparison_id: str) -> Path:
        """Write the comparison's recording now (blocking) and return its path."""
        from app.rrd import write_recording

        comparison = self.store.get_comparison(comparison_id)
        if comparison is None:
            raise LookupError(f"comparison {comparison_id!r} not found")
        rows, _ = self.store.list_jobs(comparison_id=comparison_id, limit=1000, newest_first=False)
        runs: dict[str, list[StoredEvent]] = {}
        for row in rows:
            events = self._progress_events(row["id"])
            if events:
                runs[row["method"]] = events
        if not runs:
            raise NothingRecorded("no job of this comparison reported any progress")
        frames = rows[0]["config"].get("frames") if rows else None
        seq = self.loader.load(comparison["sequence_id"], frames)
        path = write_recording(self.path(comparison_id), recording_id=comparison_id, sequence=seq, runs=runs)
        self.written += 1
        log.info("comparison %s: %s written (%s)", comparison_id, RECORDING, ", ".join(runs))
        return path

    def _progress_events(self, job_id: str) -> list[StoredEvent]:
        out: list[StoredEvent] = []
        after = 0
        while True:
            page = self.store.events_after(job_id, after, PAGE)
            out += [ev for ev in page if ev.kind in PROGRESS_KINDS]
            if len(page) < PAGE:
                return out
            after = page[-1].id
