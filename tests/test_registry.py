"""The method registry, run configs and events: shared by every method."""

from __future__ import annotations

import json

import numpy as np
import pytest

from strep_core import geometry as g
from strep_core.config import RunConfig
from strep_core.errors import Cancelled, ConfigError, MethodError
from strep_core.events import CancelToken, IterationEvent, ListSink, ResultEvent, StartEvent, parse_event
from strep_core.methods import available
from strep_core.runner import run
from strep_core.sequence import Sequence


def small_sequence(with_odometry: bool = False) -> Sequence:
    rng = np.random.default_rng(0)
    k = 6
    gt = g.se2_from_xytheta(np.stack([np.arange(k) * 2.0, np.zeros(k), np.linspace(0, 0.5, k)], 1))
    odo = g.se2_from_xytheta(np.array([0.3, -0.2, 0.05]))[None] @ gt if with_odometry else None
    return Sequence(
        frames=[rng.normal(size=(20, 2)) for _ in range(k)], name="small", unit="px", poses=gt, initial_poses=odo
    )


def test_registry_lists_every_method_with_a_description() -> None:
    methods = available()
    assert "identity" in methods
    assert all(info.description for info in methods.values())


def test_unknown_method_is_a_typed_error_naming_the_choices() -> None:
    with pytest.raises(MethodError, match=r"unknown method 'nope'; choose one of: identity"):
        run(small_sequence(), RunConfig(method="nope"))


def test_identity_run_gives_result_metrics_and_events() -> None:
    seq = small_sequence()
    sink = ListSink()
    res = run(seq, RunConfig(method="identity"), sink=sink)
    assert [e.kind for e in sink.events] == ["start", "result"]
    assert res.initial_guess == "identity"
    np.testing.assert_array_equal(res.poses, g.identity(2, len(seq)))
    # identity ATE on a straight 10 px line of 6 frames: RMS distance to the centroid
    xs = np.arange(6) * 2.0
    assert res.metrics["ate"] == pytest.approx(np.sqrt(((xs - xs.mean()) ** 2).mean()), rel=1e-9)
    assert res.metrics["frames"] == 6 and res.metrics["unit"] == "px"
    assert res.fused_map().shape == (120, 2)
    final = sink.events[-1]
    assert isinstance(final, ResultEvent) and len(final.poses) == 6


def test_odometry_is_the_default_initial_guess_when_present() -> None:
    seq = small_sequence(with_odometry=True)
    res = run(seq, RunConfig(method="identity"))
    assert res.initial_guess == "odometry"
    np.testing.assert_allclose(res.poses, seq.initial_poses)
    # the odometry here is the ground truth moved rigidly: ATE 0
    assert res.metrics["ate"] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ConfigError, match="has no odometry"):
        run(small_sequence(), RunConfig(method="identity", init="odometry"))


def test_frame_selection_in_config() -> None:
    res = run(small_sequence(), RunConfig(method="identity", frames="1:5:2"))
    assert res.sequence.indices.tolist() == [1, 3]


def test_cancel_before_start() -> None:
    token = CancelToken()
    token.set()
    with pytest.raises(Cancelled):
        run(small_sequence(), RunConfig(method="identity"), cancel=token)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"seed": -1}, "seed: Input should be greater than or equal to 0"),
        ({"optim": {"iterations": "many"}}, "optim.iterations: Input should be a valid integer"),
        ({"loss": {"window": 0}}, "loss.window: Input should be greater than or equal to 1"),
        ({"init": "magic"}, "init: Input should be"),
        ({"optim": {"lr_network": 0}}, "optim.lr_network: Input should be greater than 0"),
        ({"bogus": 1}, "bogus: Extra inputs are not permitted"),
    ],
)
def test_config_errors_are_readable(values: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        RunConfig.build(**values)


def test_config_json_round_trip(tmp_path) -> None:
    cfg = RunConfig.build(method="strep", seed=3, loss={"window": 3}, optim={"iterations": 7})
    cfg.save(tmp_path / "config.json")
    assert RunConfig.load(tmp_path / "config.json") == cfg
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read run config"):
        RunConfig.load(tmp_path / "bad.json")


def test_events_round_trip_through_json() -> None:
    events = [
        StartEvent(method="strep", sequence="s", frames=2, dims=2, unit="px", total_iterations=5, initial_guess="icp"),
        IterationEvent(iteration=1, total=5, elapsed=0.5, losses={"total": 1.5}, poses=[[0.0, 1.0, 0.1]], ate=2.0),
    ]
    for e in events:
        back = parse_event(json.loads(e.model_dump_json()))
        assert back == e
