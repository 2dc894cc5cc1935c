"""The pusher half of `ViewerServer`: the one thread that calls viser after start-up.

It wakes when a shown job has a state it has not drawn, waits until that job's throttle
interval has passed since its last push, and draws whatever is newest then (or the replay
iteration's snapshot); it also builds and removes jobs' nodes, applies control changes and
lays out the panels. Everything it reads from other threads it copies under the viewer's
lock first, and viser calls run outside it.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import viser

from app.core.config import ViewerSettings
from app.viewer import panel
from app.viewer.camera import frame_camera
from app.viewer.chart import update_chart
from app.viewer.controls import Controls
from app.viewer.panel import Job
from app.viewer.scene import layout_panels
from strep_core.runstate import Snapshot

log = logging.getLogger("app.viewer")


class Pusher:
    """Mixed into `ViewerServer`, which owns the state declared here."""

    server: viser.ViserServer
    gui: Controls
    settings: ViewerSettings
    interval: float
    stats: Any
    _lock: threading.RLock
    _wake: threading.Condition
    _jobs: dict[str, Job]
    _groups: dict[str, list[str]]
    _group_titles: dict[str, str]
    _removed: list[Job]
    _selected: str | None
    _live: bool
    _playing: bool
    _replay_it: int
    _show_gt: bool
    _point_scale: float
    _ui_rev: int
    _ui_applied: int
    _layout_dirty: set[str]
    _last_play_step: float
    _stopping: bool
    _busy: bool
    _framed: tuple[str, bool, float] | None
    _unframed_clients: set[int]

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

    def _target(self, job: Job) -> Snapshot | None:
        if self._live:
            return job.state.history.latest
        return job.state.history.at(self._replay_it)

    def _pending(self, job: Job) -> bool:
        target = self._target(job)
        return not job.built or target is not job.shown or job.state.rev != job.shown_rev

    def _selected_jobs(self) -> list[Job]:
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
        its = [j.state.iteration for j in self._selected_jobs() if j.state.history.latest is not None]
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
                    [max(j.state.total, max(j.state.iteration, 0)) for j in self._selected_jobs()],
                    default=1,
                ),
                "labels": {j.job_id: j.label for j in self._jobs.values()},
                "latest_it": self._group_max_iteration(),
                "finished": bool(self._selected_jobs()) and all(j.state.finished for j in self._selected_jobs()),
                "frame_clients": set(self._unframed_clients),
            }
            self._unframed_clients.clear()
            layout = set(self._layout_dirty)
            self._layout_dirty.clear()
            jobs = list(self._jobs.values())
            pushes: list[tuple[Job, Snapshot | None, int]] = []
            for job in self._selected_jobs():
                if self._pending(job) and now - job.last_push >= self.interval:
                    pushes.append((job, self._target(job), job.state.rev))
                    job.last_push = now
        with self.server.atomic():
            for job in removed:
                panel.destroy(job)
            for job in jobs:
                if not job.built:
                    self._build(job)
            if ui_rev != self._ui_applied:
                self._apply_ui(ui, jobs)
            for job, snap, rev in pushes:
                self._push(job, snap)
                job.shown, job.shown_rev = snap, rev
                with self._lock:
                    self.stats.pushes += 1
                    self.stats.pushes_by_job[job.job_id] = self.stats.pushes_by_job.get(job.job_id, 0) + 1
            for group in layout:
                self._layout(group)
            if pushes and ui["live"]:
                self.gui.follow(ui["max_it"], self._latest_iteration())
        with self._lock:
            self._ui_applied = ui_rev

    def _next_replay_iteration(self) -> int:
        its = sorted({s.iteration for j in self._selected_jobs() for s in j.state.history.items})
        nxt = [i for i in its if i > self._replay_it]
        if not nxt:
            self._playing = False
            self._ui_rev += 1
            return self._replay_it
        return nxt[0]

    # ---- drawing (pusher thread only) ------------------------------------------------------
    def _build(self, job: Job) -> None:
        panel.build(
            self.server,
            job,
            visible=job.group == self._selected,
            point_scale=self._point_scale,
            show_gt=self._show_gt,
            frame_nodes_max=self.settings.frame_nodes_max,
        )
        with self._lock:
            self._layout_dirty.add(job.group)
            self.stats.builds += 1

    def _members(self, group: str) -> list[Job]:
        with self._lock:
            return [self._jobs[j] for j in self._groups.get(group, []) if j in self._jobs]

    def _layout(self, group: str) -> None:
        members = self._members(group)
        boxes = [j.box_of() for j in members]
        for job, off, box in zip(members, layout_panels(boxes), boxes, strict=True):
            panel.place(job, off, box)
        # frame the camera once per shown group when every panel knows its extent, and again
        # only when the panels grew by a fifth since (a failing run spreading its map)
        measured = all(j.box is not None or j.scene.ground_truth is not None for j in members)
        span = sum(float(hi[0] - lo[0]) for lo, hi in boxes)
        framed = self._framed
        stale = framed is None or framed[:2] != (group, measured) or span > 1.2 * framed[2]
        if members and group == self._selected and stale:
            frame_camera(self.server, members)
            self._framed = (group, measured, span)

    def _apply_ui(self, ui: dict[str, Any], jobs: list[Job]) -> None:
        self.gui.apply(ui, jobs)
        selected = ui["selected"]
        if selected is not None and (self._framed is None or self._framed[0] != selected):
            self._layout(selected)
        elif selected is not None and ui["frame_clients"]:
            frame_camera(self.server, self._members(selected), clients=ui["frame_clients"])

    def _push(self, job: Job, snap: Snapshot | None) -> None:
        if snap is not None and panel.draw(job, snap, max_pose_markers=self.settings.max_pose_markers):
            with self._lock:
                self._layout_dirty.add(job.group)
        panel.update_text(job, snap)
        now = time.monotonic()
        due = now - job.chart_pushed >= self.settings.chart_interval
        if due or job.state.finished or snap is not job.state.history.latest:
            job.chart_pushed = now
            update_chart(self.server.gui, job, self._lock)
