"""The live 3D viewer: one `viser.ViserServer` fed by the jobs' event streams.

Threads. ``JobSink.emit`` runs on the thread of whoever produces events (a worker's reader,
the optimiser itself); under a short lock it applies the event to the job's `RunState`
(`strep_core.runstate.apply`: poses as float32, a snapshot in the job's bounded history)
and returns. One background *pusher* thread owns every viser call after start-up: it wakes
when a job has a state it has not shown, waits until the job's throttle interval
(``1 / max_rate_hz``) has passed since its last push, and pushes whatever is newest then. So
a burst of events costs at most one push per interval per job, the latest state wins, and
neither the optimiser nor the browsers fall behind. Jobs of groups that are not shown are not
pushed at all.

The parts, split as viser splits its server, GUI and scene APIs: this module holds the jobs,
the groups, the shared view state and the pusher; `app.viewer.panel` a job's scene nodes and
text, `app.viewer.chart` its chart, `app.viewer.controls` the shared control panel (one
presenter: every tab sees the same), `app.viewer.camera` the framing of the shown run.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import numpy as np
import viser

from app.core.config import ViewerSettings
from app.viewer.controls import Controls
from app.viewer.panel import Job
from app.viewer.pusher import Pusher
from app.viewer.scene import SequenceScene, safe_name
from strep_core.events import Event, progress_events
from strep_core.runstate import History, RunState, apply
from strep_core.sequence import Sequence

log = logging.getLogger(__name__)


@dataclass
class ViewerStats:
    """Counters since the viewer started."""

    events: int = 0
    pushes: int = 0
    pushes_by_job: dict[str, int] = field(default_factory=dict)
    builds: int = 0


class JobSink:
    """The sink of one job in a `ViewerServer`: ``emit`` stores, the pusher draws."""

    def __init__(self, viewer: ViewerServer, job_id: str) -> None:
        self.viewer = viewer
        self.job_id = job_id

    def emit(self, event: Event) -> None:
        try:
            self.viewer._accept(self.job_id, event)
        except Exception:  # a sink never breaks the run it watches
            log.exception("viewer: event of job %s dropped", self.job_id)

    @property
    def finished(self) -> bool:
        job = self.viewer._jobs.get(self.job_id)
        return bool(job and job.state.finished)


def member_rank(title: str | None, label: str, arrived: int) -> int:
    """A job's place in its group: its method's place in the title ``"<sequence>: a vs b"``
    (the comparison's order, as the page lists it), else after the methods named there."""
    names = (title or "").rpartition(": ")[2].split(" vs ")
    return names.index(label) if label in names else len(names) + arrived


class ViewerServer(Pusher):
    """A viser server showing jobs live and side by side; see the module docstring.

    Args:
        host: interface to bind; loopback by default (viser itself defaults to 0.0.0.0).
        port: port to try first; viser moves on to the next free one (see `port`). 0 picks
            a free ephemeral port.
        settings: the viewer's limits and rates (`app.core.config.ViewerSettings`, the service
            settings' ``viewer`` section); None: the defaults.
        verbose: let viser print its banner.
        admit: given a websocket client's address and handshake headers (lower-case names),
            why it is refused, or None to let it in; a refused client is closed (1008) before
            any scene data is sent. None: every client is let in.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        settings: ViewerSettings | None = None,
        verbose: bool = False,
        admit: Callable[[str | None, Mapping[str, str]], str | None] | None = None,
    ) -> None:
        self.settings = settings if settings is not None else ViewerSettings()
        self.interval = 1.0 / self.settings.max_rate_hz
        self.stats = ViewerStats()

        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._jobs: dict[str, Job] = {}
        self._groups: dict[str, list[str]] = {}
        self._group_titles: dict[str, str] = {}
        self._removed: list[Job] = []
        self._selected: str | None = None
        self._live = True
        self._playing = False
        self._replay_it = 0
        self._show_gt = True
        self._point_scale = 1.0
        self._ui_rev = 0  # bumps on any GUI-state change the pusher must apply
        self._ui_applied = -1
        self._layout_dirty: set[str] = set()
        self._last_play_step = 0.0
        self._stopping = False
        self._busy = False
        self._closed = False
        self._framed: tuple[str, bool, float] | None = None  # (group, extents known, their width) framed
        self._unframed_clients: set[int] = set()  # tabs whose canvas size just became known

        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        if admit is not None:
            self._admit_clients(admit)
        self.server.scene.set_up_direction("+z")
        self.server.on_client_connect(self._on_connect)
        #: the shared control panel
        self.gui = Controls(self.server.gui, self)
        #: its handles by name, for embedding and tests
        self.controls: dict[str, Any] = self.gui.handles
        self._thread = threading.Thread(target=self._run, name="strep-viewer-push", daemon=True)
        self._thread.start()

    def _admit_clients(self, admit: Callable[[str | None, Mapping[str, str]], str | None]) -> None:
        """Check each websocket client before viser sends it anything.

        viser has no handshake hook; its connection callbacks run, in order, before its
        producers start sending, so this one goes first and closes a refused connection.
        """
        ws = self.server._websock_server

        async def check(client: Any) -> None:
            connection = ws._live_connections.get(client.client_id)
            if connection is None:
                return
            remote = connection.remote_address
            headers = {k.lower(): v for k, v in connection.request.headers.raw_items()} if connection.request else {}
            reason = admit(str(remote[0]) if remote else None, headers)
            if reason is not None:
                log.warning("viewer: refused a websocket client: %s", reason)
                await connection.close(1008, reason[:120])

        ws._client_connect_cb.insert(0, check)

    # ---- public ----------------------------------------------------------------------------
    @property
    def port(self) -> int:
        """The port actually bound (viser skips busy ones)."""
        return self.server.get_port()

    @property
    def host(self) -> str:
        return self.server.get_host()

    @property
    def url(self) -> str:
        host = self.host
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}/"

    def sink(
        self,
        job_id: str,
        label: str,
        sequence: Sequence,
        *,
        group: str | None = None,
        group_title: str | None = None,
        select: bool | None = None,
    ) -> JobSink:
        """Register a job (or reset it if known) and return its sink.

        Args:
            job_id: unique id of the job.
            label: its name on screen (e.g. the method).
            sequence: the sequence it registers.
            group: the comparison it belongs to (jobs of a group are shown side by side);
                a job alone by default.
            group_title: the group's name in the run picker.
            select: show this group now; by default only when nothing is shown yet.
        """
        group = group or job_id
        scene = SequenceScene.from_sequence(sequence, max_points=self.settings.max_points_per_job)
        with self._lock:
            old = self._jobs.pop(job_id, None)
            if old is not None:
                self._groups[old.group].remove(job_id)
                self._removed.append(old)
            members = self._groups.setdefault(group, [])
            if group_title:
                self._group_titles[group] = group_title
            job = Job(
                job_id=job_id,
                label=label,
                group=group,
                key=self._unique_key(job_id),
                scene=scene,
                state=RunState(history=History(self.settings.history_limit), pose_dtype=np.float32),
                index=member_rank(self._group_titles.get(group), label, len(members)),
            )
            # the group's panels (left to right) and colours in its methods' order, not arrival's
            members.insert(sum(self._jobs[m].index <= job.index for m in members if m in self._jobs), job_id)
            self._jobs[job_id] = job
            if select or (select is None and self._selected is None):
                self._selected = group
            self._layout_dirty.add(group)
            self._evict()
            self._ui_rev += 1
            self._wake.notify()
        return JobSink(self, job_id)

    def load_job(
        self,
        job_id: str,
        label: str,
        sequence: Sequence,
        events: Iterable[Any],
        *,
        group: str | None = None,
        group_title: str | None = None,
        select: bool | None = None,
    ) -> JobSink:
        """Reopen a finished (or stored) job from its event log, ready to replay.

        ``events``: `Event` objects, dicts, JSON text or the job store's records (``kind`` and
        ``data``); entries that are not progress events (``status``...) are skipped.
        """
        sink = self.sink(job_id, label, sequence, group=group, group_title=group_title, select=select)
        for ev in progress_events(events):
            sink.emit(ev)
        return sink

    def remove_job(self, job_id: str) -> None:
        with self._lock:
            job = self._jobs.pop(job_id, None)
            if job is None:
                return
            self._groups[job.group].remove(job_id)
            if not self._groups[job.group]:
                del self._groups[job.group]
                self._group_titles.pop(job.group, None)
                if self._selected == job.group:
                    self._selected = next(iter(self._groups), None)
            else:
                self._layout_dirty.add(job.group)
            self._removed.append(job)
            self._ui_rev += 1
            self._wake.notify()

    def select(self, group: str) -> None:
        """Show the job or comparison ``group``."""
        with self._lock:
            if group not in self._groups:
                raise KeyError(group)
            self._show_group(group)

    def _show_group(self, group: str) -> None:
        """Show ``group`` (lock held); another run starts live: a replay iteration picked in one
        run means nothing in the next."""
        if group != self._selected:
            self._live, self._playing = True, False
        self._selected = group
        self._ui_rev += 1
        self._wake.notify()

    def set_replay(
        self, *, live: bool | None = None, iteration: int | None = None, playing: bool | None = None
    ) -> None:
        """Drive the replay controls from code (the GUI does the same)."""
        with self._lock:
            if iteration is not None:
                self._replay_it = int(iteration)
                self._live = False
            if live is not None:
                self._live = live
            if playing is not None:
                self._playing = playing
                if playing:
                    self._live = False
            self._ui_rev += 1
            self._wake.notify()

    def set_display(self, *, show_gt: bool | None = None, point_scale: float | None = None) -> None:
        """Ground truth on/off and the point-size factor (the GUI does the same)."""
        with self._lock:
            if show_gt is not None:
                self._show_gt = bool(show_gt)
            if point_scale is not None:
                self._point_scale = float(point_scale)
            self._ui_rev += 1
            self._wake.notify()

    def replay_state(self) -> dict[str, Any]:
        """The shared view state: shown group, live, playing, replay iteration, GT, point size."""
        with self._lock:
            return {
                "selected": self._selected,
                "live": self._live,
                "playing": self._playing,
                "iteration": self._replay_it,
                "show_gt": self._show_gt,
                "point_scale": self._point_scale,
            }

    def run_options(self) -> dict[str, str]:
        """The run picker's entries (as shown) -> group id, once the pusher has applied them."""
        return dict(self.gui.run_options)

    def jobs(self) -> dict[str, dict[str, Any]]:
        """A summary of each job (label, group, events, iterations kept, last iteration)."""
        with self._lock:
            out = {}
            for j in self._jobs.values():
                latest = j.state.history.latest
                out[j.job_id] = {
                    "label": j.label,
                    "group": j.group,
                    "events": j.state.events,
                    "history": len(j.state.history),
                    "iteration": None if latest is None else latest.iteration,
                    "finished": j.state.finished,
                    "pushes": self.stats.pushes_by_job.get(j.job_id, 0),
                    "key": j.key,
                    "chart": list(j.chart_series),
                    "chart_exponent": j.chart_exponent,
                    "shown_iteration": None if j.shown is None else j.shown.iteration,
                }
            return out

    def scene_node(self, name: str) -> Any:
        """The viser handle of a scene node this viewer created (``None`` if unknown)."""
        with self._lock:
            for j in self._jobs.values():
                if name in j.nodes:
                    return j.nodes[name]
                prefix = f"/jobs/{j.key}/est/f"
                if name.startswith(prefix) and name[len(prefix) :].isdigit():
                    k = int(name[len(prefix) :])
                    return j.frame_nodes[k] if k < len(j.frame_nodes) else None
        return None

    def node_names(self) -> list[str]:
        """Scene node names this viewer has created (for tests and debugging)."""
        with self._lock:
            names: list[str] = []
            for j in self._jobs.values():
                names += [n for n, h in j.nodes.items() if h is not None]
                names += [f"/jobs/{j.key}/est/f{k}" for k in range(len(j.frame_nodes))]
            return sorted(names)

    def wait_idle(self, timeout: float = 5.0) -> bool:
        """Block until everything pending is pushed (True) or ``timeout`` seconds pass."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while not self._idle():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._wake.wait(min(left, 0.02))
            return True

    def close(self) -> None:
        """Stop the pusher and the server; the port is free when this returns. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._stopping = True
            self._wake.notify_all()
        self._thread.join(timeout=10.0)
        self.server.stop()

    def __enter__(self) -> ViewerServer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _on_connect(self, client: Any) -> None:
        """Frame a tab's camera on the shown run when the tab reports a new canvas size (the
        initial camera assumes 4:3; the canvas is what the docked panel leaves, and a tab first
        reports its whole window, then the canvas beside the panel)."""
        size = (0, 0)

        def on_camera(camera: Any) -> None:
            nonlocal size
            now = (camera.image_width, camera.image_height)
            if now == size or min(now) <= 0:
                return
            size = now
            with self._lock:
                self._unframed_clients.add(client.client_id)
                self._ui_rev += 1
                self._wake.notify()

        client.camera.on_update(on_camera)

    # ---- event intake (any thread) ---------------------------------------------------------
    def _accept(self, job_id: str, event: Event) -> None:
        with self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                return
            self.stats.events += 1
            apply(job.state, event)
            if job.group == self._selected:
                self._wake.notify()

    # ---- control panel callbacks (viser's threads: they only change state) ---------------
    def _pick_group(self, group: str) -> None:
        with self._lock:
            if group in self._groups:
                self._show_group(group)

    def _play(self, playing: bool) -> None:
        with self._lock:
            if playing and self._replay_it >= self._group_max_iteration():
                self._replay_it = 0  # play from the start once at the end
        self.set_replay(playing=playing)

    # ---- bookkeeping -----------------------------------------------------------------------
    def _unique_key(self, job_id: str) -> str:
        key = safe_name(job_id)
        taken = {j.key for j in self._jobs.values()} | {j.key for j in self._removed}
        base, n = key, 2
        while key in taken:
            key, n = f"{base}_{n}", n + 1
        return key

    def _evict(self) -> None:
        while len(self._jobs) > self.settings.max_jobs:
            victims = [j for j in self._jobs.values() if j.state.finished and j.group != self._selected]
            if not victims:
                return
            job = victims[0]
            self._jobs.pop(job.job_id)
            self._groups[job.group].remove(job.job_id)
            if not self._groups[job.group]:
                del self._groups[job.group]
            self._removed.append(job)
