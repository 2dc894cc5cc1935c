"""The live 3D viewer's feed: the jobs' event stream, as stored, forwarded to `ViewerServer`.

Threads::

    supervisor --publish--> Broadcaster --+--> SSE mailboxes (event loop)
                                          +--> LiveFeed.publish: append to the inbox, return
    strep-live (one thread)   takes the inbox in order: registers a job when it starts
                              running, parses its progress events and hands them to the
                              job's viewer sink (a short lock, no viser call), answers
                              "show this job/comparison" requests
    strep-live-load           reads a job's sequence (`SequenceLoader`); meanwhile the job's
                              events wait in a bounded buffer
    viewer pusher             draws (inside `ViewerServer`, at most max_rate_hz per job)

So the supervisor never waits for the viewer, a slow read of a big sequence delays only
that job's first frame, and the viewer sees the same events, in the same order, as the
store and the SSE streams. A job joins the viewer under its comparison (``group``), so the
methods of a comparison are drawn side by side. A newly started run is shown at once unless
another run that is still going is on screen.

Finished jobs are reopened on request (`show`): their stored events are replayed into the
viewer with `ViewerServer.load_job`, then the run is shown; its replay controls work as for
a live run.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from app.services.loader import SequenceLoader
from app.store import FINAL_STATUSES, Store, StoredEvent
from strep_core.events import PROGRESS_KINDS, Event, progress_events
from strep_core.sequence import Sequence

log = logging.getLogger("strep.service")

BUFFER_LIMIT = 2000  # events kept per job while its sequence loads (then every other iteration dropped)
INBOX_LIMIT = 5000  # pending batches before queued iteration events are dropped
HOUSEKEEPING_SECONDS = 5.0
PAGE = 1000


class NothingToShow(RuntimeError):
    """The job or comparison has no progress to show yet (queued, or failed before starting)."""


class ShowFailed(RuntimeError):
    """The run cannot be shown (its sequence is gone or unreadable)."""


@dataclass
class _Feed:
    """One job as the feed knows it."""

    job_id: str
    method: str
    group: str
    sequence_id: str
    frames: str | None
    live: bool  # registered when it started running (else: reopened from the store)
    final: bool = False
    state: str = "loading"  # loading | ready | failed
    buffer: list[Event] = field(default_factory=list)
    sink: Any = None
    last_id: int = 0  # id of the last stored event taken (older ones are skipped)
    error: str | None = None


@dataclass
class _Show:
    group: str
    jobs: list[str]
    future: Future[dict[str, Any]]


class LiveFeed:
    """Feeds a `ViewerServer` from the job event stream; see the module docstring.

    Args:
        viewer: the viewer (``app.viewer.ViewerServer``).
        store: the job store (job rows, stored events of reopened jobs).
        loader: reads the sequences.
    """

    def __init__(self, viewer: Any, store: Store, loader: SequenceLoader) -> None:
        self.viewer = viewer
        self.store = store
        self.loader = loader
        self.dropped = 0  # iteration events dropped because the feed fell behind
        self._inbox: deque[tuple[Any, ...]] = deque()
        self._cond = threading.Condition()
        self._stopping = False
        self._feeds: dict[str, _Feed] = {}
        self._loading: dict[tuple[str, str | None], list[str]] = {}
        self._shows: list[_Show] = []
        self._titles: dict[str, str] = {}
        self._loads = ThreadPoolExecutor(max_workers=1, thread_name_prefix="strep-live-load")
        self._thread = threading.Thread(target=self._run, name="strep-live", daemon=True)

    # ---- any thread ----------------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def publish(self, events: list[StoredEvent]) -> None:
        """`Broadcaster` listener: queue the batch and return (never blocks on the viewer)."""
        self._post(("events", events))

    def show(
        self, *, job_id: str | None = None, comparison_id: str | None = None, timeout: float = 60.0
    ) -> dict[str, Any]:
        """Show a job (its comparison, when it has one) or a comparison in the viewer, loading
        finished jobs from their stored events. Blocks until shown.

        Returns ``{"group": id, "jobs": [ids shown]}``. Raises `NothingToShow`, `ShowFailed`,
        `LookupError` (unknown id) or `TimeoutError`.
        """
        future: Future[dict[str, Any]] = Future()
        self._post(("show", job_id, comparison_id, future))
        return future.result(timeout)

    def close(self) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=10)
        self._loads.shutdown(wait=False, cancel_futures=True)
        with self._cond:
            futures = [item[3] for item in self._inbox if item[0] == "show"]
            self._inbox.clear()
        for future in [*futures, *(show.future for show in self._shows)]:
            if not future.done():
                future.set_exception(ShowFailed("the service is shutting down"))
        self._shows.clear()

    def _post(self, item: tuple[Any, ...]) -> None:
        with self._cond:
            if self._stopping:
                if item[0] == "show":
                    item[3].set_exception(ShowFailed("the service is shutting down"))
                return
            self._inbox.append(item)
            if len(self._inbox) > INBOX_LIMIT:
                self._shed()
            self._cond.notify()

    def _shed(self) -> None:
        """Behind by more than `INBOX_LIMIT` batches: drop the queued iteration events and merge
        the batches (statuses, starts, stages and results are kept, in order)."""
        kept: deque[tuple[Any, ...]] = deque()
        for item in self._inbox:
            if item[0] == "events":
                events = [ev for ev in item[1] if ev.kind != "iteration"]
                self.dropped += len(item[1]) - len(events)
                if kept and kept[-1][0] == "events":
                    kept[-1] = ("events", kept[-1][1] + events)
                    continue
                item = ("events", events)
            kept.append(item)
        self._inbox = kept
        log.warning("viewer feed behind: %d iteration events dropped so far", self.dropped)

    # ---- the strep-live thread -----------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._inbox and not self._stopping:
                    self._cond.wait(HOUSEKEEPING_SECONDS)
                if self._stopping:
                    return
                items = list(self._inbox)
                self._inbox.clear()
            if not items:
                self.loader.expire()
                continue
            for item in items:
                try:
                    self._dispatch(item)
                except Exception:  # keep feeding whatever happens
                    log.exception("viewer feed: %s failed", item[0])

    def _dispatch(self, item: tuple[Any, ...]) -> None:
        if item[0] == "events":
            self._on_events(item[1])
        elif item[0] == "loaded":
            self._on_loaded(item[1], item[2], item[3])
        elif item[0] == "show":
            try:
                self._on_show(item[1], item[2], item[3])
            except Exception as exc:
                if not item[3].done():
                    item[3].set_exception(exc)

    def _on_events(self, events: list[StoredEvent]) -> None:
        for ev in events:
            if ev.kind == "status":
                status = json.loads(ev.data).get("status")
                if status == "running":
                    self._begin(ev)
                elif status in FINAL_STATUSES and ev.job_id in self._feeds:
                    self._feeds[ev.job_id].final = True
                continue
            feed = self._feeds.get(ev.job_id)
            if feed is None or ev.id <= feed.last_id or ev.kind not in PROGRESS_KINDS:
                continue
            feed.last_id = ev.id
            try:
                (event,) = progress_events([ev])
            except Exception:
                log.warning("viewer feed: unreadable %s event %d of %s", ev.kind, ev.id, ev.job_id)
                continue
            if feed.state == "ready":
                feed.sink.emit(event)
            elif feed.state == "loading":
                self._buffer(feed, event)

    def _begin(self, ev: StoredEvent) -> None:
        existing = self._feeds.get(ev.job_id)
        if existing is not None and existing.last_id >= ev.id:  # reopened (`show`) meanwhile
            existing.live = True
            return
        job = self.store.get_job(ev.job_id)
        if job is None:
            return
        feed = self._new_feed(job, live=True)
        feed.last_id = ev.id
        self._feeds[feed.job_id] = feed
        self._request_load(feed)

    def _new_feed(self, job: dict[str, Any], *, live: bool) -> _Feed:
        frames = job["config"].get("frames") if isinstance(job["config"], dict) else None
        return _Feed(
            job_id=job["id"],
            method=job["method"],
            group=job["comparison_id"] or job["id"],
            sequence_id=job["sequence_id"],
            frames=frames or None,
            live=live,
            final=job["status"] in FINAL_STATUSES,
        )

    @staticmethod
    def _buffer(feed: _Feed, event: Event) -> None:
        feed.buffer.append(event)
        if len(feed.buffer) > BUFFER_LIMIT:  # halve the iterations, first and newest kept
            its = [i for i, e in enumerate(feed.buffer) if e.kind == "iteration"]
            drop = set(its[1:-1:2])
            feed.buffer = [e for i, e in enumerate(feed.buffer) if i not in drop]

    def _request_load(self, feed: _Feed) -> None:
        key = (feed.sequence_id, feed.frames)
        waiting = self._loading.get(key)
        if waiting is not None:
            waiting.append(feed.job_id)
            return
        self._loading[key] = [feed.job_id]
        try:
            self._loads.submit(self._load, key)
        except RuntimeError:  # shutting down
            self._loading.pop(key, None)

    def _load(self, key: tuple[str, str | None]) -> None:
        """On the loader thread: read the sequence, post the outcome back to the feed."""
        try:
            seq = self.loader.load(*key)
        except Exception as exc:
            log.warning("viewer feed: cannot read sequence %s: %s", key[0], exc)
            self._post(("loaded", key, None, str(exc) or type(exc).__name__))
            return
        self._post(("loaded", key, seq, None))

    def _on_loaded(self, key: tuple[str, str | None], seq: Sequence | None, error: str | None) -> None:
        for job_id in self._loading.pop(key, []):
            feed = self._feeds.get(job_id)
            if feed is None or feed.state != "loading":
                continue
            if seq is None:
                feed.state, feed.error, feed.buffer = "failed", error, []
                continue
            select = self._should_select(feed.group) if feed.live else False
            feed.sink = self.viewer.load_job(
                feed.job_id,
                feed.method,
                seq,
                feed.buffer,
                group=feed.group,
                group_title=self._title(feed, seq),
                select=select,
            )
            feed.buffer = []
            feed.state = "ready"
        self._check_shows()

    def _title(self, feed: _Feed, seq: Sequence) -> str:
        if feed.group not in self._titles:
            methods = [feed.method]
            if feed.group != feed.job_id:
                comparison = self.store.get_comparison(feed.group)
                methods = comparison["methods"] if comparison else methods
            self._titles[feed.group] = f"{seq.name}: {' vs '.join(methods)}"
        return self._titles[feed.group]

    def _should_select(self, group: str) -> bool:
        """Show a run that starts unless another run still going is on screen."""
        current = self.viewer.replay_state()["selected"]
        if current is None or current == group:
            return True
        return not any(f.group == current and not f.final for f in self._feeds.values())

    # ---- reopening ----------------------------------------------------------------------------
    def _on_show(self, job_id: str | None, comparison_id: str | None, future: Future[dict[str, Any]]) -> None:
        if comparison_id is None:
            assert job_id is not None
            job = self.store.get_job(job_id)
            if job is None:
                raise LookupError(f"job {job_id!r} not found")
            comparison_id = job["comparison_id"]
            rows = [job]
        if comparison_id is not None:
            if self.store.get_comparison(comparison_id) is None:
                raise LookupError(f"comparison {comparison_id!r} not found")
            rows, _ = self.store.list_jobs(comparison_id=comparison_id, limit=1000, newest_first=False)
        group = comparison_id or rows[0]["id"]
        known = self.viewer.jobs()
        shown: list[str] = []
        for job in rows:
            if job["status"] == "queued":
                continue
            feed = self._feeds.get(job["id"])
            if feed is not None and (feed.state == "loading" or (feed.state == "ready" and job["id"] in known)):
                shown.append(job["id"])
                continue
            stored = self._stored_events(job["id"])
            events = list(progress_events(stored))
            if not events and job["status"] in FINAL_STATUSES:
                continue  # finished without any progress: nothing to draw
            feed = self._new_feed(job, live=False)
            feed.buffer = events
            feed.last_id = stored[-1].id if stored else 0  # later ones arrive through the inbox
            self._feeds[feed.job_id] = feed
            self._request_load(feed)
            shown.append(feed.job_id)
        if not shown:
            what = f"comparison {comparison_id!r}" if comparison_id else f"job {rows[0]['id']!r}"
            raise NothingToShow(f"{what} has no progress to show yet")
        self._shows.append(_Show(group, shown, future))
        self._check_shows()

    def _stored_events(self, job_id: str) -> list[StoredEvent]:
        out: list[StoredEvent] = []
        after = 0
        while True:
            page = self.store.events_after(job_id, after, PAGE)
            out += page
            if len(page) < PAGE:
                return out
            after = page[-1].id

    def _check_shows(self) -> None:
        waiting: list[_Show] = []
        for show in self._shows:
            feeds = [self._feeds.get(j) for j in show.jobs]
            if any(f is not None and f.state == "loading" for f in feeds):
                waiting.append(show)
                continue
            ready = [f.job_id for f in feeds if f is not None and f.state == "ready"]
            if not ready:
                errors = [f.error for f in feeds if f is not None and f.error]
                show.future.set_exception(ShowFailed(errors[0] if errors else "nothing could be shown"))
                continue
            try:
                self.viewer.select(show.group)
            except KeyError:
                show.future.set_exception(ShowFailed(f"{show.group} left the viewer meanwhile; try again"))
                continue
            show.future.set_result({"group": show.group, "jobs": ready})
        self._shows = waiting
