"""Fan-out of job events to live subscribers (the SSE streams).

The supervisor thread publishes events after they are stored; each subscriber has a
`Mailbox` read by its SSE generator on the event loop. A mailbox never blocks the publisher
and never grows without bound: when a subscriber falls behind, older ``iteration`` events
are dropped and only the latest is kept (statuses, stages and results are always kept). The
stored log stays complete, so a client that missed events can replay them with
``Last-Event-ID``.

Listeners (`Broadcaster.listen`) get every published batch of every job: the 3D viewer's feed
and the comparison recordings. They run on the publishing thread and only queue the events.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections import deque
from collections.abc import Callable, Iterable

from app.store import StoredEvent

log = logging.getLogger("strep.service")

MAILBOX_LIMIT = 64  # pending events per subscriber before iteration events are coalesced


class Mailbox:
    """Pending events of one subscriber; written from any thread, read on its event loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop, job_id: str, *, limit: int = MAILBOX_LIMIT) -> None:
        self.loop = loop
        self.job_id = job_id
        self.limit = limit
        self.dropped = 0
        self._items: deque[StoredEvent] = deque()
        self._lock = threading.Lock()
        self._wakeup = asyncio.Event()
        self._notified = False
        self._closed = False

    def push(self, events: Iterable[StoredEvent]) -> None:
        """Add events (any thread). Never blocks beyond a short lock."""
        with self._lock:
            if self._closed:
                return
            self._items.extend(events)
            if len(self._items) > self.limit:
                self._coalesce()
            if self._notified:
                return
            self._notified = True
        with contextlib.suppress(RuntimeError):  # the loop is closed: the subscriber is gone
            self.loop.call_soon_threadsafe(self._wake)

    def close(self) -> None:
        """No more events: the reader gets ``None`` once it has taken what is pending."""
        with self._lock:
            self._closed = True
        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(self._wake)

    def _coalesce(self) -> None:
        last_iteration = None
        for ev in reversed(self._items):
            if ev.kind == "iteration":
                last_iteration = ev
                break
        kept = deque(ev for ev in self._items if ev.kind != "iteration" or ev is last_iteration)
        self.dropped += len(self._items) - len(kept)
        self._items = kept

    def _wake(self) -> None:
        with self._lock:
            self._notified = False
        self._wakeup.set()

    async def get(self, timeout: float) -> list[StoredEvent] | None:
        """Pending events; ``[]`` after ``timeout`` seconds without any, ``None`` once closed."""
        while True:
            self._wakeup.clear()
            with self._lock:
                if self._items:
                    out = list(self._items)
                    self._items.clear()
                    return out
                if self._closed:
                    return None
            try:
                await asyncio.wait_for(self._wakeup.wait(), timeout)
            except asyncio.TimeoutError:
                return []


class Broadcaster:
    """Subscribers by job id, and listeners of every job. `publish` is called from the
    supervisor thread (and from API threads for queued and cancelled-while-queued jobs)."""

    def __init__(self) -> None:
        self._subs: dict[str, set[Mailbox]] = {}
        self._listeners: list[Callable[[list[StoredEvent]], None]] = []
        self._lock = threading.Lock()
        self._closed = False

    def listen(self, listener: Callable[[list[StoredEvent]], None]) -> None:
        """Also hand every published batch to ``listener`` (the viewer feed, recordings).

        It runs on the publishing thread, so it must only take the events and return (queue
        them); an exception it raises is logged and ignored.
        """
        with self._lock:
            self._listeners.append(listener)

    def subscribe(self, job_id: str, *, limit: int = MAILBOX_LIMIT) -> Mailbox:
        box = Mailbox(asyncio.get_running_loop(), job_id, limit=limit)
        with self._lock:
            if self._closed:
                box.close()
            else:
                self._subs.setdefault(job_id, set()).add(box)
        return box

    def unsubscribe(self, box: Mailbox) -> None:
        with self._lock:
            subs = self._subs.get(box.job_id)
            if subs is not None:
                subs.discard(box)
                if not subs:
                    del self._subs[box.job_id]

    def publish(self, events: Iterable[StoredEvent]) -> None:
        events = list(events)
        by_job: dict[str, list[StoredEvent]] = {}
        for ev in events:
            by_job.setdefault(ev.job_id, []).append(ev)
        with self._lock:
            targets = [(list(self._subs.get(job, ())), evs) for job, evs in by_job.items()]
            listeners = list(self._listeners)
        for boxes, evs in targets:
            for box in boxes:
                box.push(evs)
        if not events:
            return
        for listener in listeners:
            try:
                listener(events)
            except Exception:
                log.exception("event listener %r failed", listener)

    def subscriber_count(self, job_id: str | None = None) -> int:
        with self._lock:
            if job_id is not None:
                return len(self._subs.get(job_id, ()))
            return sum(len(s) for s in self._subs.values())

    def close(self) -> None:
        """End every live stream (service shutdown)."""
        with self._lock:
            self._closed = True
            boxes = [b for subs in self._subs.values() for b in subs]
            self._subs.clear()
        for box in boxes:
            box.close()
