"""The page's typed snapshot of one run: `run_view(state, ...) -> RunView`.

The service reduces a job's events with `strep_core.runstate.apply` and sends the page a
`RunView` after each batch (``GET /api/jobs/{id}/state``); the page draws these fields and
interprets nothing (no event kinds, stage names or file names of its own). Curves are in the
run's own terms: a learned method's x counts iterations from its starting poses (iteration 0);
a classical one's counts the frames it has placed, with the initial guess and the result as
markers (a pose graph's later passes over the frames are one step: its end marker).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from strep_core.events import stage_label
from strep_core.runstate import RunState

Axis = Literal["iterations", "frames"]
Point = tuple[float, float]
FINAL_STATUSES = ("succeeded", "failed", "cancelled", "interrupted")


class RunView(BaseModel):
    """One run as the page draws it, as of its last event."""

    method: str | None = Field(default=None, description="the method's name, from the start event")
    learned: bool = Field(description="a learned method (a loss per iteration) or a classical one")
    unit: str = Field(default="", description="the sequence's length unit ('px' or 'm'); '' before the start")
    axis: Axis = Field(description="what the curves' x counts: iterations of the learned loop, or frames placed")
    done: int = Field(description="x of the latest point (-1 before any)")
    total: int = Field(description="x at the end: iterations planned, or the sequence's frames")
    progress: str = Field(description="the progress column: '12 / 30 iterations', '64 / 64 frames (pass 2 of 2)'")
    stage: str | None = Field(default=None, description="the run's stage as the reducer names it")
    stage_text: str = Field(description="where the run is, for people (the stage column)")
    loss: list[Point] = Field(default_factory=list, description="(x, total loss) points; learned methods only")
    ate: list[Point] = Field(default_factory=list, description="(x, ATE) points, in `unit`")
    ate_start: Point | None = Field(default=None, description="classical: (0, ATE of the initial guess)")
    ate_end: Point | None = Field(default=None, description="classical: (frames, ATE of the result)")
    ate_now: float | None = Field(default=None, description="the result's ATE, else the latest one")
    point_l2: float | None = Field(default=None, description="the result's point-wise L2 to the true map")
    seconds: float | None = Field(default=None, description="the run's wall time, else seconds so far")
    finished: bool = Field(default=False, description="the result event arrived")


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def figure(v: float) -> str:
    """3 significant digits, never an exponent from 1000 up: ``0.456``, ``184``, ``1099``."""
    return f"{v:.0f}" if abs(v) >= 1000 else f"{v:.3g}"


_g = figure


def _pass(state: RunState, it: int) -> tuple[int, int, int]:
    """A classical run's iteration -> (frame, pass, passes): a pose graph counts 2 per frame."""
    k = max(state.frames, 1)
    passes = max(1, -(-state.total // k))
    return (it - 1) % k + 1 if it > 0 else 0, (it - 1) // k + 1 if it > 0 else 1, passes


def _stage_text(state: RunState, view: RunView, status: str | None) -> str:
    unit = f" {state.unit}" if state.unit else ""
    it = state.iteration
    if status == "queued":
        return "queued"
    if state.finished and status in (None, "succeeded"):
        start = _num(state.metrics.get("initial_ate")) if not view.learned else state.start_ate
        end = view.ate_now
        where = f"{state.frames} frames, " if not view.learned else f"{it} iterations, "
        ates = ""
        if end is not None:
            ates = f"ATE {_g(start)} → {_g(end)}{unit}" if start is not None else f"ATE {_g(end)}{unit}"
        secs = f" in {figure(view.seconds)} s" if view.seconds is not None else ""
        return f"done{secs}: {where}{ates}".rstrip(", ")
    if status in FINAL_STATUSES:
        at = f" at {view.progress}" if it > 0 else ""
        return f"{status}{at}"
    if state.finished or state.stage == "write":
        return "writing files"
    if state.stage is None:
        return "loading the sequence…" if status == "running" else "waiting for the run…"
    if not view.learned:
        if it <= 0:
            return "starting…" if state.stage == "prepare" else f"{stage_label(state.stage)}…"
        _, p, passes = _pass(state, it)
        latest = state.history.latest
        ate = f", ATE {_g(latest.ate)}{unit} so far" if latest and latest.ate is not None and p == 1 else ""
        return f"placing frames{ate}" if p == 1 else f"pass {p} of {passes} over the placed frames"
    start = f"ATE {_g(state.start_ate)}{unit}" if state.start_ate is not None else ""
    if it == 0:
        head = f"{stage_label(state.stage)} done" if state.stage and state.stage.startswith("init") else "starting"
        return f"{head}: {start}" if start else head
    if it > 0:
        return f"optimising from {start}" if start else "optimising"
    if state.stage_done is not None and state.stage_total:
        return f"{stage_label(state.stage)} {state.stage_done} / {state.stage_total}…"
    return f"{stage_label(state.stage)}…"


def run_view(state: RunState, *, learned: bool, status: str | None = None) -> RunView:
    """The page's snapshot of ``state``; ``status`` is the job's (queued, running, succeeded...)
    when a job store knows it, which words the stage of a run that ended early."""
    curves = state.history.curves()
    unit = state.unit
    view = RunView(
        method=state.method,
        learned=learned,
        unit=unit,
        axis="iterations" if learned else "frames",
        done=-1,
        total=state.total if learned else state.frames,
        progress="",
        stage=state.stage,
        stage_text="",
        finished=state.finished,
    )
    latest = state.history.latest
    view.point_l2 = _num(state.metrics.get("point_l2"))
    view.seconds = _num(state.metrics.get("wall_seconds")) or (latest.elapsed if latest else None)
    if state.finished:
        view.ate_now = _num(state.metrics.get("ate"))
    elif latest is not None:
        view.ate_now = next((s.ate for s in reversed(state.history.items) if s.ate is not None), None)
    if learned:
        xs, ys = curves.get("loss/total", ((), ()))
        view.loss = [(float(x), float(y)) for x, y in zip(xs, ys, strict=True)]
        xs, ys = curves.get("ate", ((), ()))
        view.ate = [(float(x), float(y)) for x, y in zip(xs, ys, strict=True)]
        view.done = state.iteration
        view.progress = f"{max(view.done, 0)} / {state.total} iterations" if state.total else ""
    else:
        k = state.frames
        xs, ys = curves.get("ate", ((), ()))
        # later passes revisit the frames: the curve is the first pass, the rest ends in the result
        view.ate = [(float(x), float(y)) for x, y in zip(xs, ys, strict=True) if 0 < x <= k]
        initial = _num(state.metrics.get("initial_ate"))
        view.ate_start = (0.0, initial) if initial is not None else None
        view.ate_end = (float(k), view.ate_now) if state.finished and view.ate_now is not None else None
        frame, p, passes = _pass(state, max(state.iteration, 0))
        if state.finished:  # (a method may report no frames: the result places them all)
            frame, p = k, passes
        view.done = frame if p == 1 else k
        if k:
            view.progress = f"{frame if state.iteration > 0 or state.finished else 0} / {k} frames"
            if passes > 1 and not state.finished:
                view.progress += f" (pass {p} of {passes})"
    view.stage_text = _stage_text(state, view, status)
    return view
