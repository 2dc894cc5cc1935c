"""The run-state reducer: real event sequences folded into the state every view draws."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from strep_core.config import RunConfig
from strep_core.events import PROGRESS_KINDS, Event, ListSink, ResultEvent, StageEvent, progress_events
from strep_core.runner import load_input, run
from strep_core.runstate import PAGE_RULES, REDUCERS, History, RunState, apply


@pytest.fixture(scope="module")
def strep_events() -> list:
    """A real strep run on the small 2D sample: a warm start, 12 iterations, an event every 4."""
    seq = load_input("sample:sim2d-small")
    sink = ListSink()
    run(seq, RunConfig(method="strep", optim={"iterations": 12, "event_interval": 4}), sink=sink)
    return sink.events


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


def _page_entry(events: list) -> dict:
    """The page's entry of a job after ``events`` (as JSON, as the stream carries them), by the rules
    of `PAGE_RULES`: the same interpreter as ``applyRules`` in static/app.js."""

    def pick(ev: dict, path: str):
        for key in path.split("."):
            ev = None if ev is None else ev.get(key)
        return ev

    entry: dict = {"loss": [], "ate": []}
    for event in events:
        ev = event.model_dump(mode="json")
        for r in PAGE_RULES.get(ev["kind"], []):
            if any(pick(ev, path) != want for path, want in r.get("if", {}).items()):
                continue
            value = (
                r["value"]
                if "value" in r
                else [pick(ev, p) for p in r["from"]]
                if r.get("push")
                else pick(ev, r["from"])
            )
            if r.get("push"):
                if all(v is not None for v in value):
                    entry[r["push"]].append(value)
            elif not (r.get("skip_null") and value is None):
                entry[r["set"]] = value
    return entry


def test_the_page_rules_name_event_fields_and_agree_with_the_reducer(strep_events) -> None:
    """The page's rules (served to static/app.js) read fields the events have, and give the
    figures `apply` gives: the planned and done iterations, start ATE, curves and metrics."""
    classes = {cls.model_fields["kind"].default: cls for cls in Event.__args__[0].__args__}
    assert set(PAGE_RULES) <= set(REDUCERS)
    for kind, rules in PAGE_RULES.items():
        for r in rules:
            paths = r.get("from", [])
            for path in [*([paths] if isinstance(paths, str) else paths), *r.get("if", {})]:
                assert path.split(".")[0] in classes[kind].model_fields, (kind, path)
    entry = _page_entry(strep_events)
    state, _ = _reduce(strep_events)
    assert entry["started"] and (entry["total"], entry["iteration"]) == (state.total, state.iteration) == (12, 12)
    assert entry["startAte"] == state.start_ate and entry["metrics"] == state.metrics
    xs, ys = state.history.curves()["loss/total"]
    assert entry["loss"] == [[int(x), y] for x, y in zip(xs, ys, strict=True)]
    xs, ys = state.history.curves()["ate"]
    assert [it for it, _ in entry["ate"]] == list(xs)
    # the last snapshot's ATE is the result's (the final pass), the page keeps the last event's
    assert [a for _, a in entry["ate"]][:-1] == list(ys[:-1]) and entry["ate"][-1][1] == pytest.approx(ys[-1], rel=1e-2)
    assert entry["lastAte"] == entry["ate"][-1][1] and entry["stage"] == "init:multiway"


def test_a_strep_run_reduces_to_its_result(strep_events) -> None:
    kinds = [e.kind for e in strep_events]
    assert kinds == ["stage", "start", "iteration", "iteration", "iteration", "iteration", "result"]
    state, seen = _reduce(strep_events)
    result = strep_events[-1]
    assert isinstance(result, ResultEvent)
    assert (state.method, state.total, state.started, state.finished) == ("strep", 12, True, True)
    assert state.events == 7
    assert state.metrics == result.metrics
    np.testing.assert_array_equal(state.poses, np.asarray(result.poses))
    assert state.poses.dtype == np.float64 and state.poses.shape == (64, 3)
    # the warm start's ATE is the ATE of iteration 0
    assert state.start_ate == strep_events[2].ate and 0.05 < state.start_ate < 0.1
    assert state.history.iterations() == [0, 4, 8, 12]
    final = state.history.latest
    assert final.ate == pytest.approx(result.metrics["ate"]) and final.elapsed == result.wall_seconds
    assert final.losses == strep_events[-2].losses  # the result repeats iteration 12: its losses kept
    # the stage: the warm start until iteration 0 is done, then optimising
    assert [s[0] for s in seen] == ["init:multiway"] * 3 + ["optimise"] * 4
    # texts change at the stage, the start, the switch to optimising and the result only
    assert [s[2] for s in seen] == [1, 2, 2, 3, 3, 3, 4]


def test_steps_say_what_each_event_did(strep_events) -> None:
    state = RunState()
    steps = [apply(state, ev).step for ev in strep_events]
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
