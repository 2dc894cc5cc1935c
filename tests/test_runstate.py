"""The run-state reducer: real event sequences folded into the state every view draws."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from strep_core.config import RunConfig
from strep_core.events import PROGRESS_KINDS, ListSink, ResultEvent, StageEvent, progress_events
from strep_core.runner import load_input, run
from strep_core.runstate import REDUCERS, History, RunState, apply
from strep_core.runview import figure, run_view


@pytest.fixture(scope="module")
def strep_events() -> list:
    """A real strep run on the small 2D sample: a warm start, 12 iterations, an event every 4."""
    seq = load_input("sample:sim2d-small")
    sink = ListSink()
    run(seq, RunConfig(method="strep", optim={"iterations": 12, "event_interval": 4}), sink=sink)
    return sink.events


def _milestones(events: list) -> list:
    """The events without the warm start's progress (stage events that carry ``done``)."""
    return [e for e in events if not (e.kind == "stage" and e.done is not None)]


@pytest.fixture(scope="module")
def icp_events() -> list:
    sink = ListSink()
    run(load_input("sample:sim2d-small"), RunConfig(method="icp"), sink=sink)
    return sink.events


def _reduce(events, **kw) -> tuple[RunState, list[RunState]]:
    state = RunState(**kw)
    seen = []
    for ev in events:
        apply(state, ev)
        seen.append((state.stage, state.step, state.rev))
    return state, seen


def test_every_event_kind_has_one_reducer() -> None:
    assert set(REDUCERS) == PROGRESS_KINDS == {"start", "stage", "iteration", "result"}


@pytest.fixture(scope="module")
def multiway_events() -> list:
    sink = ListSink()
    run(load_input("sample:sim2d-small"), RunConfig(method="multiway"), sink=sink)
    return sink.events


def test_a_learned_run_is_drawn_in_iterations_from_its_starting_poses(strep_events) -> None:
    state, _ = _reduce(strep_events, keep_poses=False)
    assert state.poses is None and state.frames == 64 and state.unit == "px"
    view = run_view(state, learned=True, status="succeeded")
    assert (view.axis, view.done, view.total, view.progress) == ("iterations", 12, 12, "12 / 12 iterations")
    xs, ys = state.history.curves()["ate"]
    assert view.ate == list(zip(xs, ys, strict=True)) and view.ate[0][0] == 0
    assert [x for x, _ in view.loss] == [4, 8, 12] and view.ate_start is None and view.ate_end is None
    start, end = state.start_ate, state.metrics["ate"]
    assert view.stage_text.startswith("done in ")
    assert view.stage_text.endswith(f": 12 iterations, ATE {start:.3g} → {end:.3g} px"), view.stage_text
    # while it runs: the warm start, then the optimisation from its ATE
    state, texts = RunState(), []
    for ev in strep_events[:-1]:
        texts.append(run_view(apply(state, ev), learned=True, status="running").stage_text)
    warm = [t for t in texts if t.startswith("warm start")]
    assert warm[0] == "warm start (multiway)…"
    assert any(t.startswith("warm start (multiway) ") and t.endswith(" / 128…") for t in warm)  # its steps
    assert warm[-1] == f"warm start (multiway) done: ATE {start:.3g} px"
    assert texts[-1] == f"optimising from ATE {start:.3g} px"
    assert run_view(state, learned=True, status="failed").stage_text == "failed at 12 / 12 iterations"
    # long runs read in whole seconds (before: "done in 1.1e+03 s")
    assert figure(1098.8) == "1099" and figure(0.4561) == "0.456" and figure(184.2) == "184"


def test_a_pose_graph_is_drawn_in_frames_with_its_result_as_one_step(multiway_events) -> None:
    """The x axis counts the 64 frames (not the 128 events' iterations); the loop-closure pass
    and the graph's optimisation are one step to the end marker; the start marker is the guess."""
    state, _ = _reduce(multiway_events, keep_poses=False)
    assert state.total == 128
    view = run_view(state, learned=False, status="succeeded")
    assert (view.axis, view.done, view.total, view.progress) == ("frames", 64, 64, "64 / 64 frames")
    assert view.loss == [] and [x for x, _ in view.ate] == [10, 20, 30, 40, 50, 60]
    assert view.ate_start == (0, pytest.approx(state.metrics["initial_ate"]))
    assert view.ate_end == (64, pytest.approx(state.metrics["ate"]))
    assert view.ate_start[1] / view.ate_end[1] > 100  # decades apart: the page draws a log axis
    assert view.stage_text.endswith(f"64 frames, ATE 56 → {state.metrics['ate']:.3g} px")
    # during the second pass the progress says so, in frames
    state = RunState()
    for ev in multiway_events:
        apply(state, ev)
        if ev.kind == "iteration" and ev.iteration == 80:
            mid = run_view(state, learned=False, status="running")
            assert (mid.progress, mid.stage_text) == (
                "16 / 64 frames (pass 2 of 2)",
                "pass 2 of 2 over the placed frames",
            )


def test_a_strep_run_reduces_to_its_result(strep_events) -> None:
    assert any(e.kind == "stage" and e.done for e in strep_events)  # the warm start reports its steps
    kinds = [e.kind for e in _milestones(strep_events)]
    assert kinds == ["stage", "start", "iteration", "iteration", "iteration", "iteration", "result"]
    state, seen = _reduce(strep_events)
    result = strep_events[-1]
    assert isinstance(result, ResultEvent)
    assert (state.method, state.total, state.started, state.finished) == ("strep", 12, True, True)
    assert state.events == len(strep_events)
    assert state.metrics == result.metrics
    np.testing.assert_array_equal(state.poses, np.asarray(result.poses))
    assert state.poses.dtype == np.float64 and state.poses.shape == (64, 3)
    # the warm start's ATE is the ATE of iteration 0
    assert state.start_ate == _milestones(strep_events)[2].ate and 0.05 < state.start_ate < 0.1
    assert state.history.iterations() == [0, 4, 8, 12]
    final = state.history.latest
    assert final.ate == pytest.approx(result.metrics["ate"]) and final.elapsed == result.wall_seconds
    assert final.losses == strep_events[-2].losses  # the result repeats iteration 12: its losses kept
    # the stage: the warm start until iteration 0 is done, then optimising
    progress = len(strep_events) - 7  # the warm start's progress events
    assert [s[0] for s in seen] == ["init:multiway"] * (3 + progress) + ["optimise"] * 4
    # texts change at the stage, the start, the switch to optimising and the result only
    # (and at each of the warm start's progress events: its text counts the steps)
    p = progress
    assert [s[2] for s in seen] == [1, *range(2, 2 + p), 2 + p, 2 + p, 3 + p, 3 + p, 3 + p, 4 + p]


def test_steps_say_what_each_event_did(strep_events) -> None:
    state = RunState()
    steps = [apply(state, ev).step for ev in _milestones(strep_events)]
    stage, start, it0, it4, *_, res = steps
    assert (stage.kind, stage.iteration, stage.message) == ("stage", 0, "stage init:multiway")
    assert stage.snapshot is None and not stage.final
    assert start.message.startswith("strep on sim2d-small (64 frames, 2D, 12 iterations planned")
    assert it0.snapshot is not None and it0.snapshot.iteration == 0 and it0.message is None
    assert it4.iteration == 4 and it4.snapshot.poses is state.history.items[1].poses
    assert res.final and res.iteration == 12 and res.message.startswith("finished after ")
    assert res.snapshot is state.history.latest


def test_a_stage_after_the_iterations_sits_at_the_last_posed_iteration(icp_events) -> None:
    state, _ = _reduce(icp_events)
    last = state.pose_iteration
    assert last == state.iteration > 0
    apply(state, StageEvent(stage="write", elapsed=1.0))
    assert (state.stage, state.step.iteration, state.step.elapsed) == ("write", last, 1.0)


def test_an_unknown_kind_is_counted_and_never_taken_for_an_iteration(icp_events) -> None:
    @dataclass
    class Warning:
        kind: str = "warning"
        iteration: int = 99

    state, _ = _reduce(icp_events[:3])
    before = (state.history.iterations(), state.rev, state.stage, state.total)
    apply(state, Warning())
    assert state.step is None and state.events == 4
    assert (state.history.iterations(), state.rev, state.stage, state.total) == before


def test_the_stored_log_reduces_like_the_live_stream(icp_events) -> None:
    """What the service stores (JSON, with status records between) gives the same state."""
    stored = [{"kind": "status", "status": "running"}] + [e.model_dump(mode="json") for e in icp_events]
    live, _ = _reduce(icp_events, pose_dtype=np.float32, history=History(4))
    replayed, _ = _reduce(progress_events(stored), pose_dtype=np.float32, history=History(4))
    assert replayed.events == live.events == len(icp_events)
    assert replayed.history.iterations() == live.history.iterations()
    assert len(live.history) <= 4 and live.history.dropped > 0
    assert live.poses.dtype == np.float32
    np.testing.assert_array_equal(replayed.poses, live.poses)
    assert (replayed.stage, replayed.start_ate, replayed.metrics) == (live.stage, live.start_ate, live.metrics)
