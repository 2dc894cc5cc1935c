"""One run's state, rebuilt from its events by one reducer: ``apply(state, event) -> state``.

Every view draws from a `RunState` instead of interpreting events itself: the viser viewer
(``app.viewer``), the Rerun recorder (``app.rrd``) and the page (``static/``, which renders the
typed snapshots `strep_core.runview.run_view` makes of a state on the server). How each event
kind changes the state is written once, in `REDUCERS`,
keyed by the kinds of `strep_core.events.Event`; an event of any other kind is counted and
otherwise ignored (never taken for an iteration). Adding a kind: docs/design/extending.md.

numpy only: no viewer library is imported here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core.events import Event, IterationEvent, ResultEvent, StageEvent, StartEvent, stage_label

# --------------------------------------------------------------------------------------------
# History


@dataclass
class Snapshot:
    """A run's state after one event.

    Attributes:
        iteration: iterations done (the event's ``iteration``; the result's count at the end).
        elapsed: seconds since the run started.
        poses: ``(K, 3|6)`` pose vectors, or ``None`` before the first poses.
        losses: loss terms of the event.
        ate: ATE in the sequence unit, when known.
    """

    iteration: int
    elapsed: float
    poses: np.ndarray | None
    losses: dict[str, float]
    ate: float | None


class History:
    """Snapshots at the event interval, at most ``limit`` of them.

    When full, every other snapshot is dropped (the first and the newest are kept), so the
    history always spans the whole run at an even, coarser step: memory stays bounded by
    ``limit * K * 6`` pose values (poses unchanged since the previous snapshot are shared,
    not copied).
    """

    def __init__(self, limit: int = 256) -> None:
        if limit < 4:
            raise ValueError("a history keeps at least 4 snapshots")
        self.limit = limit
        self.items: list[Snapshot] = []
        self.dropped = 0

    def __len__(self) -> int:
        return len(self.items)

    def append(self, snap: Snapshot) -> None:
        if self.items and self.items[-1].iteration == snap.iteration:
            self.items[-1] = snap  # the same iteration again (e.g. the result): latest wins
            return
        self.items.append(snap)
        if len(self.items) > self.limit:
            keep = [*self.items[:-1:2], self.items[-1]]
            self.dropped += len(self.items) - len(keep)
            self.items = keep

    @property
    def latest(self) -> Snapshot | None:
        return self.items[-1] if self.items else None

    def at(self, iteration: int) -> Snapshot | None:
        """The newest snapshot with ``iteration <=`` the given one (the first if none is)."""
        if not self.items:
            return None
        its = [s.iteration for s in self.items]
        i = int(np.searchsorted(its, iteration, side="right")) - 1
        return self.items[max(i, 0)]

    def iterations(self) -> list[int]:
        return [s.iteration for s in self.items]

    def curves(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per curve name (``loss/<term>``, ``ate``): ``(iterations, values)`` float64 arrays."""
        out: dict[str, tuple[list[float], list[float]]] = {}
        for s in self.items:
            for term, v in s.losses.items():
                xs, ys = out.setdefault(f"loss/{term}", ([], []))
                xs.append(s.iteration)
                ys.append(v)
            if s.ate is not None:
                xs, ys = out.setdefault("ate", ([], []))
                xs.append(s.iteration)
                ys.append(s.ate)
        # a loss term that is off (weight 0: the optimiser reports it as 0.0) is no curve
        return {
            k: (np.asarray(x, np.float64), np.asarray(y, np.float64))
            for k, (x, y) in out.items()
            if k == "ate" or any(v != 0.0 for v in y)
        }


# --------------------------------------------------------------------------------------------
# The state and its reducer


@dataclass(frozen=True)
class Step:
    """What the last event did to a `RunState`: views draw it without looking at the event.

    Attributes:
        kind: the event's kind.
        iteration: where the event sits on the iteration timeline (>= 0).
        elapsed: seconds since the run started, at the event.
        message: a line for logs (start, stages, the result), or ``None``.
        snapshot: the snapshot the event added to the history, or ``None``.
        final: the event finished the run (the result).
    """

    kind: str
    iteration: int
    elapsed: float
    message: str | None = None
    snapshot: Snapshot | None = None
    final: bool = False


@dataclass
class RunState:
    """Everything the views show of one run, as of its last event.

    Attributes:
        history: snapshots for replay and the loss / ATE curves.
        pose_dtype: dtype poses are kept in (float32 for the live viewer's memory, float64
            where the figures are written out).
        method, total: from the start event (``total``: iterations planned, raised by any
            iteration event that plans more).
        frames, unit: the sequence's frame count and length unit, from the start event.
        keep_poses: keep pose vectors (False for views that draw no poses, such as the page:
            their history then holds figures only).
        stage: the stage the run is in: a `StageEvent`'s name, ``"prepare"`` between the
            start event and iteration 0, ``"optimise"`` from the first iteration after 0.
        start_ate: ATE of the starting poses (iteration 0, after any warm start).
        started, finished: a start event / the result event arrived.
        metrics: the result's metrics.
        poses: ``(K, 3|6)`` the latest pose vectors, or ``None``.
        pose_iteration: the iteration of ``poses`` (-1 before any).
        events: events applied, of every kind.
        rev: bumps whenever something other than the history changes (texts to redraw).
        step: what the last event did, or ``None`` after an event of an unknown kind.
    """

    history: History = field(default_factory=History)
    pose_dtype: Any = np.float64
    method: str | None = None
    total: int = 0
    frames: int = 0
    unit: str = ""
    keep_poses: bool = True
    stage: str | None = None
    stage_done: int | None = None
    stage_total: int | None = None
    start_ate: float | None = None
    started: bool = False
    finished: bool = False
    metrics: dict[str, Any] = field(default_factory=dict)
    poses: np.ndarray | None = None
    pose_iteration: int = -1
    events: int = 0
    rev: int = 0
    step: Step | None = None

    @property
    def iteration(self) -> int:
        """The latest snapshot's iteration (-1 before any)."""
        latest = self.history.latest
        return -1 if latest is None else latest.iteration


def _start(state: RunState, event: StartEvent) -> Step:
    state.method, state.total, state.started = event.method, event.total_iterations, True
    state.frames, state.unit = event.frames, event.unit
    if state.stage in (None, "load"):
        state.stage = "prepare"  # the optimiser sets up until its iteration 0
    state.rev += 1
    message = (
        f"{event.method} on {event.sequence} ({event.frames} frames, {event.dims}D, "
        f"{event.total_iterations} iterations planned, initial guess {event.initial_guess})"
    )
    return Step("start", 0, 0.0, message=message)


def _stage(state: RunState, event: StageEvent) -> Step:
    state.stage = event.stage
    state.stage_done, state.stage_total = event.done, event.total  # a long stage's progress
    state.rev += 1
    return Step("stage", max(state.pose_iteration, 0), event.elapsed, message=f"stage {event.stage}")


def _iteration(state: RunState, event: IterationEvent) -> Step:
    state.total = max(state.total, event.total)
    if event.iteration == 0:
        state.start_ate = event.ate
    elif state.stage != "optimise":
        state.stage = "optimise"  # the warm start (``init:...``) is over
        state.rev += 1
    if event.poses is not None and state.keep_poses:
        state.poses = np.asarray(event.poses, dtype=state.pose_dtype)
        state.pose_iteration = event.iteration
    snap = Snapshot(event.iteration, event.elapsed, state.poses, dict(event.losses), event.ate)
    state.history.append(snap)
    return Step("iteration", event.iteration, event.elapsed, snapshot=snap)


def _result(state: RunState, event: ResultEvent) -> Step:
    latest = state.history.latest
    it = max(event.iterations, latest.iteration if latest else 0)
    ate = event.metrics.get("ate")
    losses = latest.losses if latest is not None and latest.iteration == it else {}
    state.finished = True
    state.metrics = dict(event.metrics)
    if state.keep_poses:
        state.poses = np.asarray(event.poses, dtype=state.pose_dtype)
    state.pose_iteration = it
    snap = Snapshot(it, event.wall_seconds, state.poses, losses, float(ate) if isinstance(ate, (int, float)) else None)
    state.history.append(snap)
    state.rev += 1
    message = f"finished after {event.wall_seconds:.2f} s"
    return Step("result", it, event.wall_seconds, message=message, snapshot=snap, final=True)


#: How each event kind changes a run's state: the one dispatch table over event kinds.
REDUCERS: dict[str, Callable[[RunState, Any], Step]] = {
    "start": _start,
    "stage": _stage,
    "iteration": _iteration,
    "result": _result,
}


def apply(state: RunState, event: Event | Any) -> RunState:
    """Apply one event to ``state`` (in place: histories are not copied) and return it.

    ``state.step`` then says what the event did; an event of a kind without a reducer only
    counts in ``state.events`` and leaves ``state.step`` ``None``.
    """
    state.events += 1
    reducer = REDUCERS.get(getattr(event, "kind", None) or "")
    state.step = None if reducer is None else reducer(state, event)
    return state


# --------------------------------------------------------------------------------------------
# Text


def stage_line(
    stage: str | None, snap: Snapshot | None, *, start_ate: float | None, unit: str, finished: bool
) -> str | None:
    """The line that says where a run is: ``"stage: warm start (multiway)"`` before its first
    iteration event, ``"stage: warm start (multiway) done, ATE 0.069 px"`` at iteration 0,
    ``"stage: optimising (from ATE 0.069 px)"`` after; None once finished or before anything.
    (`strep_core.runview` words the page's stage column by the same rules.)"""
    if finished:
        return None
    it = None if snap is None else snap.iteration
    start = f"ATE {start_ate:.4g} {unit}" if start_ate is not None else ""
    if it == 0:  # (also when replaying iteration 0)
        head = f"{stage_label(stage)} done" if stage and stage.startswith("init") else "starting"
        return f"stage: {head}" + (f", {start}" if start else "")
    if stage == "optimise" or (it is not None and it > 0 and stage != "write"):
        return "stage: optimising" + (f" (from {start})" if start else "")
    return None if stage is None else f"stage: {stage_label(stage)}"
