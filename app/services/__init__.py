"""The service behind the API: store, sequences, jobs and event fan-out, opened together."""

from __future__ import annotations

import logging
import multiprocessing
import os
from pathlib import Path
from typing import IO

from app.core.config import Settings
from app.services.events import Broadcaster
from app.services.jobs import JobService
from app.services.sequences import SequenceService
from app.store import Store

log = logging.getLogger("strep.service")


class DataDirBusy(RuntimeError):
    """Another service already uses this data directory."""


def _lock_data_dir(data_dir: Path) -> IO[str]:
    """An exclusive lock on ``data_dir/.lock`` for this process's lifetime (POSIX; no-op elsewhere)."""
    handle = open(data_dir / ".lock", "a+")  # noqa: SIM115 - held until Service.close
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        return handle
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        raise DataDirBusy(f"another STREP service is using {data_dir}") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle


class Service:
    """Everything the API needs, owned by the application's lifespan."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self._lock = _lock_data_dir(settings.data_dir)
        for plugin in settings.plugins:
            __import__(plugin)
        self.ctx = multiprocessing.get_context("spawn")
        self.store = Store(settings.db_path)
        self.broadcaster = Broadcaster()
        self.sequences = SequenceService(settings, self.store, self.ctx)
        self.jobs = JobService(settings, self.store, self.broadcaster, self.sequences, self.ctx)

    def start(self) -> None:
        self.sequences.clean()
        self.settings.results_dir.mkdir(parents=True, exist_ok=True)
        self.jobs.start()

    def close(self) -> None:
        try:
            self.jobs.close()
            self.broadcaster.close()
            self.sequences.close()
            self.store.close()
        finally:
            self._lock.close()
