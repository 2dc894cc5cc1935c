"""The service behind the API: store, sequences, jobs, event fan-out and viewers, opened together.

Every stored job event goes through one `Broadcaster`: to the SSE streams, to the comparison
recordings (`ComparisonRecordings`) and, when the 3D viewer is enabled, to its feed
(`LiveFeed` -> `app.viewer.ViewerServer`).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from collections.abc import Mapping
from pathlib import Path
from typing import IO, TYPE_CHECKING

from app.core.config import Settings, is_loopback
from app.core.guard import LocalOnly
from app.services.broadcast import Broadcaster
from app.services.comparison_recordings import ComparisonRecordings
from app.services.jobs import JobService
from app.services.live import LiveFeed
from app.services.loader import SequenceLoader
from app.services.sequences import SequenceService
from app.store import Store

if TYPE_CHECKING:
    from app.viewer.viewer import ViewerServer

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


def check_data_dir_free(data_dir: Path) -> None:
    """`DataDirBusy` when another service holds ``data_dir`` (checked before starting a server,
    so a busy folder is one line, not a failed start-up's traceback); a missing folder is free."""
    if (data_dir / ".lock").exists():
        _lock_data_dir(data_dir).close()  # taken and released at once


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
        self.loader = SequenceLoader(self.jobs.scene_path)  # the scenes the workers wrote
        self.recordings = ComparisonRecordings(settings, self.store, self.loader)
        self.broadcaster.listen(self.recordings.on_events)
        self.viewer: ViewerServer | None = None
        self.live: LiveFeed | None = None

    def start(self) -> None:
        from app.rrd import disable_rerun_telemetry

        disable_rerun_telemetry()  # here and in the workers (they inherit the environment)
        self.sequences.clean()
        self.settings.results_dir.mkdir(parents=True, exist_ok=True)
        if self.settings.viewer_enabled:
            self._start_viewer()
        self.jobs.start()

    def _start_viewer(self) -> None:
        """The live 3D viewer, on the API's host; viser takes the next port when one is busy."""
        from app.viewer import ViewerServer

        if not is_loopback(self.settings.host):
            log.warning(
                "the 3D viewer on %s has no authentication: anyone who reaches it sees the runs", self.settings.host
            )
        admit = None
        if self.settings.api_token is None:  # loopback mode: the API's Host and Origin checks
            local = LocalOnly(self.settings)

            def admit(client: str | None, headers: Mapping[str, str]) -> str | None:
                refused = local.refusal(client, headers)
                return None if refused is None else refused.detail

        self.viewer = ViewerServer(
            host=self.settings.host, port=self.settings.viewer_port, settings=self.settings.viewer, admit=admit
        )
        self.live = LiveFeed(self.viewer, self.store, self.loader)
        self.live.start()
        self.broadcaster.listen(self.live.publish)
        log.info("3D viewer at %s", self.viewer.url)

    def close(self) -> None:
        try:
            self.jobs.close()
            if self.live is not None:
                self.live.close()
            self.recordings.close()
            if self.viewer is not None:
                self.viewer.close()  # frees its port
            self.broadcaster.close()
            self.sequences.close()
            self.store.close()
        finally:
            self._lock.close()
