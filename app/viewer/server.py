"""The live 3D viewer: one `viser.ViserServer` fed by the jobs' event streams.

Threads. ``JobSink.emit`` runs on the thread of whoever produces events (a worker's reader,
the optimiser itself); it converts the poses, stores the job's latest state and appends it to
the job's bounded `History`, under a short lock, and returns. One background *pusher*
thread owns every viser call after start-up: it wakes when a job has a state it has not
shown, waits until the job's throttle interval (``1 / max_rate_hz``) has passed since its last
push, and pushes whatever is newest then. So a burst of events costs at most one push per
interval per job, the latest state wins, and neither the optimiser nor the browsers fall
behind. Jobs of groups that are not shown are not pushed at all.

Scene (shared by every browser tab; viser replays it to late joiners)::

    /jobs/<job>                  frame: the job's panel, offset along +x (side by side)
    /jobs/<job>/label            label: "<label>" and the current iteration / ATE
    /jobs/<job>/est              frame: display anchor G_0 inv(T_0) (identity without GT)
    /jobs/<job>/est/f<k>         point cloud of frame k (float32, strided), posed by T_k
                                 (sequences of more than ``frame_nodes_max`` frames instead
                                 get one cloud /jobs/<job>/map re-sent at each push)
    /jobs/<job>/trajectory       line segments: estimated positions
    /jobs/<job>/poses            batched axes: at most ``max_pose_markers`` poses
    /jobs/<job>/gt               line segments: ground-truth trajectory (when known)

GUI (shared by all tabs: one presenter, everybody sees the same; per-tab state would need
per-client scenes and multiply the traffic): the run (job or comparison) to show, follow
live, play/pause, an iteration slider over the recorded history, ground truth on/off, a
point-size factor, and per job a folder with its current figures and a uPlot chart of its
loss terms and ATE. The control panel is docked on the right, beside the scene; the camera is
framed on the shown run with clip planes scaled to it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import numpy as np
import viser

from app.viewer.scene import (
    History,
    SequenceScene,
    Snapshot,
    bbox,
    display_anchor,
    label_position,
    layout_panels,
    poses_to_matrices,
    progress_events,
    rotations_to_wxyz,
    safe_name,
    stage_line,
    union_bbox,
)
from strep_core.events import Event, IterationEvent, ResultEvent, StageEvent, StartEvent
from strep_core.sequence import Sequence

log = logging.getLogger(__name__)

NO_RUN = "(no runs yet)"
GT_COLOR = (120, 120, 120)
TRAJECTORY_COLORS = [(230, 80, 40), (40, 120, 230), (40, 170, 90), (170, 70, 200), (220, 170, 30)]
CHART_INTERVAL = 0.5  # seconds between chart updates of a job (its text follows every push)
CURVE_COLORS = ["#e6502a", "#2878e6", "#28aa5a", "#aa46c8", "#dcaa1e", "#555555"]


def camera_pose(box: tuple[np.ndarray, np.ndarray], *, fov: float, aspect: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera ``(position, look_at)`` that shows ``box`` (world, z up) from above, slightly
    tilted, filling most of a view of vertical field of view ``fov`` (radians) and ``aspect``
    (width / height); it looks at the middle of the box."""
    lo, hi = np.asarray(box[0], np.float64), np.asarray(box[1], np.float64)
    center, extent = (lo + hi) / 2.0, hi - lo
    tan_v = math.tan(fov / 2.0)
    distance = max(
        float(extent[0]) / (2.0 * tan_v * aspect * 0.8),  # width across the view, a margin each side
        float(max(extent[1], extent[2])) / (2.0 * tan_v * 0.8),  # depth and height up the view
        1e-6,
    )
    direction = np.array([0.0, -0.3, 1.0]) / math.hypot(0.3, 1.0)
    return center + distance * direction, center


@dataclass
class ViewerStats:
    """Counters since the viewer started."""

    events: int = 0
    pushes: int = 0
    pushes_by_job: dict[str, int] = field(default_factory=dict)
    builds: int = 0


def loss_exponent(curves: list[np.ndarray]) -> int:
    """Power of ten in which to draw loss curves: ``e`` with the largest finite ``|value|`` in
    ``[10**e, 10**(e+1))`` when it lies outside ``[0.01, 1000)`` (uPlot's axis labels show
    three decimals: a Chamfer loss of 1e-4 reads as 0), else 0."""
    v = np.abs(np.concatenate([np.ravel(c) for c in curves])) if curves else np.zeros(0)
    v = v[np.isfinite(v)]
    if v.size == 0 or v.max() <= 0:
        return 0
    e = int(np.floor(np.log10(v.max())))
    return e if e < -2 or e > 2 else 0


@dataclass
class _Job:
    job_id: str
    label: str
    group: str
    key: str
    scene: SequenceScene
    history: History
    index: int
    method: str | None = None
    total: int = 0
    stage: str | None = None
    start_ate: float | None = None  # ATE of the starting poses (iteration 0: after the warm start)
    finished: bool = False
    metrics: dict[str, Any] = field(default_factory=dict)
    last_poses: np.ndarray | None = None
    events: int = 0
    # pusher-owned
    built: bool = False
    shown: Snapshot | None = None
    shown_rev: int = -1
    last_push: float = -math.inf
    nodes: dict[str, Any] = field(default_factory=dict)
    frame_nodes: list[Any] = field(default_factory=list)
    chart: Any = None
    chart_series: tuple[str, ...] = ()
    chart_exponent: int = 0  # loss curves are drawn in units of 10**chart_exponent
    chart_pushed: float = -math.inf
    box: tuple[np.ndarray, np.ndarray] | None = None
    shown_box: tuple[np.ndarray, np.ndarray] | None = None  # the estimated map as last pushed (framing)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rev: int = 0  # bumps when something besides the snapshot changes (result text, layout)


def _set_value(handle: Any, value: Any) -> None:
    """Set a GUI input from the server (its callbacks see ``client is None`` and ignore it)."""
    handle.value = value


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
        return bool(job and job.finished)


class ViewerServer:
    """A viser server showing jobs live and side by side; see the module docstring.

    Args:
        host: interface to bind; loopback by default (viser itself defaults to 0.0.0.0).
        port: port to try first; viser moves on to the next free one (see `port`). 0 picks
            a free ephemeral port.
        max_points_per_job: points drawn per job (frames evenly strided).
        max_rate_hz: pushes per second per job, at most.
        history_limit: snapshots kept per job for replay (then decimated 2:1).
        max_pose_markers: pose axes drawn per job.
        frame_nodes_max: up to this many frames, each frame is its own cloud moved by its
            pose (a push sends K poses); above, one fused cloud is re-sent per push.
        max_jobs: jobs kept; beyond, the oldest finished ones are removed.
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
        max_points_per_job: int = 30_000,
        max_rate_hz: float = 10.0,
        history_limit: int = 256,
        max_pose_markers: int = 64,
        frame_nodes_max: int = 512,
        max_jobs: int = 32,
        verbose: bool = False,
        admit: Callable[[str | None, Mapping[str, str]], str | None] | None = None,
    ) -> None:
        if max_rate_hz <= 0:
            raise ValueError("max_rate_hz must be positive")
        self.max_points_per_job = max_points_per_job
        self.interval = 1.0 / max_rate_hz
        self.history_limit = history_limit
        self.max_pose_markers = max_pose_markers
        self.frame_nodes_max = frame_nodes_max
        self.max_jobs = max_jobs
        self.stats = ViewerStats()

        self._lock = threading.RLock()
        self._wake = threading.Condition(self._lock)
        self._jobs: dict[str, _Job] = {}
        self._groups: dict[str, list[str]] = {}
        self._group_titles: dict[str, str] = {}
        self._removed: list[_Job] = []
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
        self._build_gui()
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
        scene = SequenceScene.from_sequence(sequence, max_points=self.max_points_per_job)
        with self._lock:
            old = self._jobs.pop(job_id, None)
            if old is not None:
                self._groups[old.group].remove(job_id)
                self._removed.append(old)
            members = self._groups.setdefault(group, [])
            job = _Job(
                job_id=job_id,
                label=label,
                group=group,
                key=self._unique_key(job_id),
                scene=scene,
                history=History(self.history_limit),
                index=len(members),
            )
            members.append(job_id)
            self._jobs[job_id] = job
            if group_title:
                self._group_titles[group] = group_title
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
        return dict(self._run_options)

    def jobs(self) -> dict[str, dict[str, Any]]:
        """A summary of each job (label, group, events, iterations kept, last iteration)."""
        with self._lock:
            out = {}
            for j in self._jobs.values():
                latest = j.history.latest
                out[j.job_id] = {
                    "label": j.label,
                    "group": j.group,
                    "events": j.events,
                    "history": len(j.history),
                    "iteration": None if latest is None else latest.iteration,
                    "finished": j.finished,
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
        poses = None
        if isinstance(event, (IterationEvent, ResultEvent)) and event.poses is not None:
            poses = np.asarray(event.poses, dtype=np.float32)
        with self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                return
            job.events += 1
            self.stats.events += 1
            if isinstance(event, StartEvent):
                job.method, job.total = event.method, event.total_iterations
                if job.stage in (None, "load"):
                    job.stage = "prepare"  # the optimiser sets up until its iteration 0
                job.rev += 1
            elif isinstance(event, StageEvent):
                job.stage = event.stage
                job.rev += 1
            elif isinstance(event, IterationEvent):
                job.total = max(job.total, event.total)
                if event.iteration == 0:
                    job.start_ate = event.ate
                elif job.stage != "optimise":
                    job.stage = "optimise"  # the warm start (``init:...``) is over
                    job.rev += 1
                if poses is not None:
                    job.last_poses = poses
                job.history.append(
                    Snapshot(event.iteration, event.elapsed, job.last_poses, dict(event.losses), event.ate)
                )
            elif isinstance(event, ResultEvent):
                job.finished = True
                job.metrics = dict(event.metrics)
                job.last_poses = poses
                latest = job.history.latest
                it = max(event.iterations, latest.iteration if latest else 0)
                ate = event.metrics.get("ate")
                losses = latest.losses if latest is not None and latest.iteration == it else {}
                job.history.append(
                    Snapshot(
                        it, event.wall_seconds, poses, losses, float(ate) if isinstance(ate, (int, float)) else None
                    )
                )
                job.rev += 1
            if job.group == self._selected:
                self._wake.notify()

    # ---- GUI (callbacks run on viser's threads: they only change state) -------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False)
        gui.main_panel.dock_right()  # beside the scene, not over it (the camera frames the rest)
        self._gui_run = gui.add_dropdown("Run", (NO_RUN,), initial_value=NO_RUN)
        self._gui_live = gui.add_checkbox("Follow live", initial_value=True)
        self._gui_play = gui.add_button_group("Replay", ("Play", "Pause"))
        self._gui_iter = gui.add_slider("Iteration", min=0, max=1, step=1, initial_value=0)
        self._gui_gt = gui.add_checkbox("Ground truth", initial_value=True)
        self._gui_size = gui.add_slider("Point size", min=0.1, max=5.0, step=0.1, initial_value=1.0)
        self._gui_status = gui.add_markdown("")
        self._run_options: dict[str, str] = {}
        #: the shared GUI controls by name (their handles), for embedding and tests
        self.controls: dict[str, Any] = {
            "run": self._gui_run,
            "live": self._gui_live,
            "replay": self._gui_play,
            "iteration": self._gui_iter,
            "ground_truth": self._gui_gt,
            "point_size": self._gui_size,
        }

        @self._gui_run.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is None:
                return
            group = self._run_options.get(self._gui_run.value)
            if group is not None:
                with self._lock:
                    if group in self._groups:
                        self._show_group(group)

        @self._gui_live.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                self.set_replay(live=self._gui_live.value, playing=False if self._gui_live.value else None)

        @self._gui_play.on_click
        def _(ev: viser.GuiEvent) -> None:
            playing = self._gui_play.value == "Play"
            with self._lock:
                if playing and self._replay_it >= self._group_max_iteration():
                    self._replay_it = 0  # play from the start once at the end
            self.set_replay(playing=playing)

        @self._gui_iter.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                self.set_replay(iteration=int(self._gui_iter.value), playing=False)

        @self._gui_gt.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                self.set_display(show_gt=bool(self._gui_gt.value))

        @self._gui_size.on_update
        def _(ev: viser.GuiEvent) -> None:
            if ev.client is not None:
                self.set_display(point_scale=float(self._gui_size.value))

    # ---- the pusher ------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._lock:
                if self._stopping:
                    return
                timeout = self._next_wait()
                if timeout is None or timeout > 0:
                    self._wake.wait(timeout)
                if self._stopping:
                    return
                self._busy = True
            try:
                self._step()
            except Exception:
                log.exception("viewer: push failed")
                time.sleep(self.interval)
            finally:
                with self._lock:
                    self._busy = False
                    self._wake.notify_all()

    def _target(self, job: _Job) -> Snapshot | None:
        if self._live:
            return job.history.latest
        return job.history.at(self._replay_it)

    def _pending(self, job: _Job) -> bool:
        target = self._target(job)
        return not job.built or target is not job.shown or job.rev != job.shown_rev

    def _selected_jobs(self) -> list[_Job]:
        return [self._jobs[j] for j in self._groups.get(self._selected or "", [])]

    def _next_wait(self) -> float | None:
        """Seconds until the pusher has something to do; ``None``: wait for a wake-up."""
        if self._removed or self._ui_rev != self._ui_applied or self._layout_dirty:
            return 0.0
        now = time.monotonic()
        waits = [job.last_push + self.interval - now for job in self._selected_jobs() if self._pending(job)]
        if self._playing:
            waits.append(self._last_play_step + self.interval - now)
        return max(min(waits), 0.0) if waits else None

    def _idle(self) -> bool:
        if self._busy or self._removed or self._ui_rev != self._ui_applied or self._layout_dirty:
            return False
        if any(not j.built for j in self._jobs.values()):
            return False
        return not any(self._pending(job) for job in self._selected_jobs())

    def _latest_iteration(self) -> int:
        with self._lock:
            return self._group_max_iteration()

    def _group_max_iteration(self) -> int:
        its = [j.history.latest.iteration for j in self._selected_jobs() if j.history.latest is not None]
        return max(its, default=0)

    def _step(self) -> None:
        now = time.monotonic()
        with self._lock:
            removed, self._removed = self._removed, []
            if self._playing and now - self._last_play_step >= self.interval:
                self._last_play_step = now
                self._replay_it = self._next_replay_iteration()
            ui_rev = self._ui_rev
            ui: dict[str, Any] = {
                "groups": {g: list(m) for g, m in self._groups.items()},
                "titles": dict(self._group_titles),
                "selected": self._selected,
                "live": self._live,
                "playing": self._playing,
                "replay_it": self._replay_it,
                "show_gt": self._show_gt,
                "point_scale": self._point_scale,
                "max_it": max(
                    [
                        max(j.total, j.history.latest.iteration if j.history.latest else 0)
                        for j in self._selected_jobs()
                    ],
                    default=1,
                ),
                "labels": {j.job_id: j.label for j in self._jobs.values()},
                "latest_it": self._group_max_iteration(),
                "frame_clients": set(self._unframed_clients),
            }
            self._unframed_clients.clear()
            layout = set(self._layout_dirty)
            self._layout_dirty.clear()
            jobs = list(self._jobs.values())
            pushes: list[tuple[_Job, Snapshot | None, int]] = []
            for job in self._selected_jobs():
                if self._pending(job) and now - job.last_push >= self.interval:
                    pushes.append((job, self._target(job), job.rev))
                    job.last_push = now
        with self.server.atomic():
            for job in removed:
                self._destroy(job)
            for job in jobs:
                if not job.built:
                    self._build(job)
            if ui_rev != self._ui_applied:
                self._apply_ui(ui, jobs)
            for job, snap, rev in pushes:
                self._push(job, snap, ui)
                job.shown, job.shown_rev = snap, rev
                with self._lock:
                    self.stats.pushes += 1
                    self.stats.pushes_by_job[job.job_id] = self.stats.pushes_by_job.get(job.job_id, 0) + 1
            for group in layout:
                self._layout(group)
            if pushes and ui["live"]:
                self._gui_iter.max = max(int(ui["max_it"]), 1)  # totals become known after the job appears
                _set_value(self._gui_iter, min(self._latest_iteration(), self._gui_iter.max))
        with self._lock:
            self._ui_applied = ui_rev

    def _next_replay_iteration(self) -> int:
        its = sorted({s.iteration for j in self._selected_jobs() for s in j.history.items})
        nxt = [i for i in its if i > self._replay_it]
        if not nxt:
            self._playing = False
            self._ui_rev += 1
            return self._replay_it
        return nxt[0]

    # ---- drawing (pusher thread only) ------------------------------------------------------
    def _build(self, job: _Job) -> None:
        scene, sc, root = self.server.scene, job.scene, f"/jobs/{job.key}"
        marker = sc.marker_scale()
        visible = job.group == self._selected
        job.nodes[root] = scene.add_frame(root, show_axes=False, visible=visible)
        job.nodes[f"{root}/label"] = scene.add_label(
            f"{root}/label", job.label, position=tuple(label_position(self._box_of(job))), anchor="bottom-center"
        )
        job.nodes[f"{root}/est"] = scene.add_frame(f"{root}/est", show_axes=False, visible=False)
        size = 0.3 * marker * self._point_scale
        if len(sc) <= self.frame_nodes_max:
            job.frame_nodes = [
                scene.add_point_cloud(f"{root}/est/f{k}", pts, color, point_size=size, precision="float32")
                for k, (pts, color) in enumerate(zip(sc.frames, sc.colors, strict=True))
            ]
        else:  # one fused cloud, in display coordinates; only its points change
            job.nodes[f"{root}/map"] = scene.add_point_cloud(
                f"{root}/map",
                np.concatenate(sc.frames),
                sc.point_colors(),
                point_size=size,
                precision="float32",
                visible=False,
            )
        color = TRAJECTORY_COLORS[job.index % len(TRAJECTORY_COLORS)]
        job.nodes[f"{root}/trajectory"] = scene.add_line_segments(
            f"{root}/trajectory",
            np.zeros((1, 2, 3), np.float32),
            color,
            thickness=2.0,
            thickness_units="screen",
            visible=False,
        )
        job.nodes[f"{root}/poses"] = scene.add_batched_axes(
            f"{root}/poses",
            np.tile([1.0, 0.0, 0.0, 0.0], (1, 1)),
            np.zeros((1, 3)),
            axes_length=2.0 * marker,
            axes_radius=0.15 * marker,
            visible=False,
        )
        if sc.ground_truth is not None:
            pos = sc.ground_truth[:, :3, 3]
            job.nodes[f"{root}/gt"] = scene.add_line_segments(
                f"{root}/gt",
                np.stack([pos[:-1], pos[1:]], 1),
                GT_COLOR,
                thickness=1.5,
                thickness_units="screen",
                visible=self._show_gt,
            )
        with self.server.gui.add_folder(job.label, visible=visible) as folder:
            job.nodes["gui/folder"] = folder
            job.nodes["gui/text"] = self.server.gui.add_markdown(f"**{job.label}**: waiting for events")
        job.built = True
        with self._lock:
            self._layout_dirty.add(job.group)
            self.stats.builds += 1

    def _destroy(self, job: _Job) -> None:
        for node in job.frame_nodes:
            node.remove()
        scene_nodes = [n for n in job.nodes if not n.startswith("gui/")]
        for name in sorted(scene_nodes, key=lambda n: -n.count("/")):  # children first
            job.nodes[name].remove()
        for name in ("gui/chart", "gui/text", "gui/folder"):
            handle = job.nodes.get(name)
            if handle is not None:
                handle.remove()
        job.nodes.clear()
        job.frame_nodes.clear()

    def _box_of(self, job: _Job) -> tuple[np.ndarray, np.ndarray]:
        """A panel's extent: the ground-truth map and the estimated map as last laid out
        (a unit box before either is known)."""
        box = union_bbox(job.scene.gt_bbox(), job.box)
        return box if box is not None else (np.zeros(3), np.ones(3))

    def _members(self, group: str) -> list[_Job]:
        with self._lock:
            return [self._jobs[j] for j in self._groups.get(group, []) if j in self._jobs]

    def _layout(self, group: str) -> None:
        members = self._members(group)
        boxes = [self._box_of(j) for j in members]
        for job, off, box in zip(members, layout_panels(boxes), boxes, strict=True):
            job.offset = off
            if job.built:
                job.nodes[f"/jobs/{job.key}"].position = off
                job.nodes[f"/jobs/{job.key}/label"].position = label_position(box)
        # frame the camera once per shown group when every panel knows its extent, and again
        # only when the panels grew by a fifth since (a failing run spreading its map)
        measured = all(j.box is not None or j.scene.ground_truth is not None for j in members)
        span = sum(float(hi[0] - lo[0]) for lo, hi in boxes)
        framed = self._framed
        stale = framed is None or framed[:2] != (group, measured) or span > 1.2 * framed[2]
        if members and group == self._selected and stale:
            self._frame_camera(group)
            self._framed = (group, measured, span)

    def _apply_ui(self, ui: dict[str, Any], jobs: list[_Job]) -> None:
        selected = ui["selected"]
        options: dict[str, str] = {}
        for group, members in ui["groups"].items():
            title = ui["titles"].get(group) or " vs ".join(ui["labels"].get(m, m) for m in members)
            text = title if group == members[0] and len(members) == 1 and title == group else f"{title} [{group}]"
            while text in options:
                text += "'"
            options[text] = group
        self._run_options = options
        shown = [t for t, g in options.items() if g == selected]
        if options:
            self._gui_run.options = tuple(options)
            if shown:
                _set_value(self._gui_run, shown[0])
        else:
            self._gui_run.options = (NO_RUN,)
            _set_value(self._gui_run, NO_RUN)
        for job in jobs:
            if not job.built:
                continue
            visible = job.group == selected
            job.nodes[f"/jobs/{job.key}"].visible = visible
            job.nodes["gui/folder"].visible = visible
            gt = job.nodes.get(f"/jobs/{job.key}/gt")
            if gt is not None:
                gt.visible = ui["show_gt"]
            size = 0.3 * job.scene.marker_scale() * ui["point_scale"]
            for node in job.frame_nodes:
                node.point_size = size
            if f"/jobs/{job.key}/map" in job.nodes:
                job.nodes[f"/jobs/{job.key}/map"].point_size = size
        _set_value(self._gui_live, ui["live"])
        self._gui_iter.max = max(int(ui["max_it"]), 1)
        shown_it = ui["latest_it"] if ui["live"] else ui["replay_it"]  # never a value left from another run
        _set_value(self._gui_iter, min(int(shown_it), self._gui_iter.max))
        _set_value(self._gui_gt, ui["show_gt"])
        _set_value(self._gui_size, ui["point_scale"])
        mode = "live" if ui["live"] else ("playing" if ui["playing"] else "paused")
        self._gui_status.content = f"{len(ui['groups'])} run(s); replay: {mode}"
        if selected is not None and (self._framed is None or self._framed[0] != selected):
            self._layout(selected)
        elif selected is not None and ui["frame_clients"]:
            self._frame_camera(selected, clients=ui["frame_clients"])

    def _frame_camera(self, group: str, *, clients: set[int] | None = None) -> None:
        """Point every tab's camera (or only ``clients``) and the initial camera at ``group``."""
        members = self._members(group)
        if not members:
            return
        box = None
        for job in members:  # the ground truth and the estimate as shown now (not as laid out)
            shown = job.shown_box or self._box_of(job)
            for lo, hi in (b for b in (job.scene.gt_bbox(), shown) if b is not None):
                box = union_bbox(box, (lo + job.offset, hi + job.offset))
        assert box is not None
        size = float(max(np.max(box[1] - box[0]), 1e-6))
        # clip planes scaled to the scene: viser's default far plane (1000) hides maps in pixels
        near, far = max(1e-3, 1e-4 * size), max(1000.0, 20.0 * size)
        camera = self.server.initial_camera
        position, look_at = camera_pose(box, fov=camera.fov, aspect=4 / 3)
        camera.near, camera.far = near, far
        # position first: viser's camera position setter drags look_at along with it
        camera.position = tuple(position)
        camera.look_at = tuple(look_at)
        for client_id, client in self.server.get_clients().items():
            if clients is not None and client_id not in clients:
                continue
            cam = client.camera
            try:
                width, height, fov = cam.image_width, cam.image_height, cam.fov
            except AssertionError:  # the client has not reported its camera yet
                width, height, fov = 0, 0, camera.fov
            aspect = width / height if width > 0 and height > 0 else 4 / 3
            position, look_at = camera_pose(box, fov=fov, aspect=aspect)
            cam.near, cam.far = near, far
            cam.position = position
            cam.look_at = look_at

    def _push(self, job: _Job, snap: Snapshot | None, ui: dict[str, Any]) -> None:
        root = f"/jobs/{job.key}"
        if snap is not None and snap.poses is not None:
            est = poses_to_matrices(snap.poses)
            anchor = display_anchor(est, job.scene.ground_truth)
            shown = anchor[None] @ est
            est_node = job.nodes[f"{root}/est"]
            est_node.wxyz = rotations_to_wxyz(anchor[:3, :3])
            est_node.position = anchor[:3, 3]
            est_node.visible = True
            if job.frame_nodes:
                wxyz = rotations_to_wxyz(est[:, :3, :3])
                for node, q, t in zip(job.frame_nodes, wxyz, est[:, :3, 3], strict=True):
                    node.wxyz = q
                    node.position = t
            else:
                cloud = job.nodes[f"{root}/map"]
                cloud.points = job.scene.fuse(shown)
                cloud.visible = True
            pos = shown[:, :3, 3]
            traj = job.nodes[f"{root}/trajectory"]
            traj.points = np.stack([pos[:-1], pos[1:]], 1).astype(np.float32)
            traj.visible = True
            step = max(1, math.ceil(len(pos) / self.max_pose_markers))
            axes = job.nodes[f"{root}/poses"]
            axes.batched_wxyzs = rotations_to_wxyz(shown[::step, :3, :3]).astype(np.float32)
            axes.batched_positions = pos[::step].astype(np.float32)
            axes.visible = True
            box = bbox(job.scene.fuse(shown, max_points=4096))
            job.shown_box = box  # from scratch the estimate spreads beyond the ground truth's box
            # the panel's extent follows the estimate too (a failing run's map can be twice the
            # ground truth's), with hysteresis so that re-layouts stay rare
            size, old = box[1][:2] - box[0][:2], None if job.box is None else job.box[1][:2] - job.box[0][:2]
            if old is None or not np.all((0.7 * old <= size) & (size <= 1.05 * old)):
                job.box = box
                with self._lock:
                    self._layout_dirty.add(job.group)
        self._update_text(job, snap)
        now = time.monotonic()
        if now - job.chart_pushed >= CHART_INTERVAL or job.finished or snap is not job.history.latest:
            job.chart_pushed = now
            self._update_chart(job)

    def _update_text(self, job: _Job, snap: Snapshot | None) -> None:
        lines = [f"**{job.label}** ({job.method or '?'})"]
        if snap is not None:
            total = f"/{job.total}" if job.total else ""
            lines.append(f"iteration {snap.iteration}{total}, {snap.elapsed:.1f} s")
            terms = {k: v for k, v in snap.losses.items() if v != 0.0}  # a term that is off reports 0
            if terms:
                lines.append(", ".join(f"{k} {v:.4g}" for k, v in terms.items()))
            if snap.ate is not None:
                lines.append(f"ATE {snap.ate:.4g} {job.scene.unit}")
        stage = stage_line(job.stage, snap, start_ate=job.start_ate, unit=job.scene.unit, finished=job.finished)
        if stage:
            lines.append(stage)
        if job.finished:
            m = job.metrics
            parts = [
                f"{k} {m[k]:.4g}" for k in ("ate", "point_l2", "wall_seconds") if isinstance(m.get(k), (int, float))
            ]
            lines.append("finished: " + ", ".join(parts))
        job.nodes["gui/text"].content = "  \n".join(lines)
        label = job.label if snap is None else f"{job.label}  it {snap.iteration}"
        if snap is not None and snap.ate is not None:
            label += f"  ATE {snap.ate:.3g}"
        job.nodes[f"/jobs/{job.key}/label"].text = label

    def _update_chart(self, job: _Job) -> None:
        with self._lock:
            curves = job.history.curves()
        if not curves:
            return
        names = tuple(sorted(curves, key=lambda n: (n == "ate", n != "loss/total", n)))
        xs = np.unique(np.concatenate([curves[n][0] for n in names]))
        # one x axis for all series: rows where a series has no value repeat its previous value
        data = [xs]
        for n in names:
            x, y = curves[n]
            idx = np.clip(np.searchsorted(x, xs, side="right") - 1, 0, len(x) - 1)
            data.append(y[idx])
        same = job.chart is not None and job.chart_series == names
        if not same:  # the loss unit is chosen once per chart, so its axis label stays put
            job.chart_exponent = loss_exponent([d for n, d in zip(names, data[1:], strict=True) if n != "ate"])
        unit = 10.0**-job.chart_exponent
        data = [data[0]] + [d if n == "ate" else d * unit for n, d in zip(names, data[1:], strict=True)]
        if same:
            job.chart.data = tuple(data)
            return
        if job.chart is not None:
            job.chart.remove()
        series = [viser.uplot.Series(label="iteration")]
        for i, n in enumerate(names):
            series.append(
                viser.uplot.Series(
                    label=n.removeprefix("loss/"),
                    stroke=CURVE_COLORS[i % len(CURVE_COLORS)],
                    width=2,
                    scale="ate" if n == "ate" else "loss",
                )
            )
        axes = [viser.uplot.Axis()]
        if any(n != "ate" for n in names):
            e = job.chart_exponent
            axes.append(viser.uplot.Axis(scale="loss", label=f"loss (x 1e{e})" if e else "loss"))
        if "ate" in names:
            axes.append(viser.uplot.Axis(scale="ate", side=1, label=f"ATE ({job.scene.unit})"))
        with job.nodes["gui/folder"]:
            job.chart = self.server.gui.add_uplot(
                data=tuple(data),
                series=tuple(series),
                scales={"x": viser.uplot.Scale(time=False, auto=True), "loss": {"auto": True}, "ate": {"auto": True}},
                axes=tuple(axes),
                aspect=1.6,
            )
        job.nodes["gui/chart"] = job.chart
        job.chart_series = names

    # ---- bookkeeping -----------------------------------------------------------------------
    def _unique_key(self, job_id: str) -> str:
        key = safe_name(job_id)
        taken = {j.key for j in self._jobs.values()} | {j.key for j in self._removed}
        base, n = key, 2
        while key in taken:
            key, n = f"{base}_{n}", n + 1
        return key

    def _evict(self) -> None:
        while len(self._jobs) > self.max_jobs:
            victims = [j for j in self._jobs.values() if j.finished and j.group != self._selected]
            if not victims:
                return
            job = victims[0]
            self._jobs.pop(job.job_id)
            self._groups[job.group].remove(job.job_id)
            if not self._groups[job.group]:
                del self._groups[job.group]
            self._removed.append(job)
