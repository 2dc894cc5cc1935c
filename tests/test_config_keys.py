"""Config keys: one name per setting, and the flat names of earlier versions still read
(`strep_core.config.migrate`) from a saved config.json, ``--set`` and REST job bodies."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import pytest

from strep_core.config import RENAMED, RunConfig
from strep_core.errors import ConfigError

BENCH = Path(__file__).resolve().parents[1] / "docs" / "bench"


def _get(data: dict[str, Any], dotted: str) -> Any:
    for part in dotted.split("."):
        data = data[part]
    return data


def _old_rows() -> list[dict[str, Any]]:
    rows = []
    for path in sorted(BENCH.glob("*.json")):
        rows += [r["config"] for r in json.loads(path.read_text()).get("rows", []) if "config" in r]
    return rows


def test_every_setting_has_one_name() -> None:
    """No two settings share a leaf name with different units: the classical frames interval and
    the optimiser's iterations interval, the pose graph's loop radius (sequence unit) and the
    loss's (fraction of the scale)."""
    cfg = RunConfig()
    assert cfg.classical.event_interval_frames == 10 and cfg.optim.event_interval == 5
    assert cfg.classical.posegraph.loop_radius is None and cfg.loss.loop_radius_fraction == 0.5
    assert "event_interval" not in type(cfg.classical).model_fields
    assert "loop_radius" not in type(cfg.loss).model_fields
    flat = [name for name in type(cfg.classical).model_fields if "_" in name and name.split("_")[0] in {"icp", "kiss"}]
    assert flat == []  # no prefixed flat fields left
    for old, new in RENAMED.items():  # every new path exists, every old one is gone
        _get(cfg.model_dump(), new)
        with pytest.raises(KeyError):
            _get(cfg.model_dump(), old)


def test_the_benchmark_records_configs_read_under_the_new_names(caplog: pytest.LogCaptureFixture) -> None:
    rows = _old_rows()
    assert len(rows) >= 100  # docs/bench/*.json: every run's config, saved with the flat names
    for old in rows:
        with caplog.at_level(logging.WARNING, logger="strep_core.config"):
            cfg = RunConfig.model_validate(old)
        new = json.loads(cfg.model_dump_json())
        for old_key, new_key in RENAMED.items():
            section, key = old_key.split(".", 1)
            if key not in old[section]:  # older rows predate some settings: the default then
                continue
            value = old[section][key]
            assert _get(new, new_key) == (list(value) if isinstance(value, tuple) else value), old_key
        assert RunConfig.model_validate(new) == cfg  # and the new form reads back the same
    assert "classical.icp_scales -> classical.icp.scales" in caplog.text
    assert "loss.loop_radius -> loss.loop_radius_fraction" in caplog.text


def test_an_old_config_json_reruns_to_the_same_resolved_config(tmp_path: Path) -> None:
    """A real old config (the laser-keyframes row of the CARMEN benchmark: global scan matcher,
    global loop closures, velocity prior) re-run with ``--config`` gives the run of its new form."""
    from strep_cli.main import main

    old = next(r for r in _old_rows() if r["profile"] == "laser-keyframes" and r["classical"]["icp_global"] == "on")
    old = {**old, "method": "multiway", "frames": "0:12", "init": "auto", "start": "pose-graph"}
    (tmp_path / "old.json").write_text(json.dumps(old))
    new = RunConfig.model_validate(old)
    assert new.classical.scanmatch.consecutive == "on" and new.classical.posegraph.loop_global == "on"
    new.save(tmp_path / "new.json")
    outs = {}
    for name in ("old", "new"):
        argv = ["run", "sample:sim2d-small", "--config", str(tmp_path / f"{name}.json"), "--out", str(tmp_path / name)]
        assert main([*argv, "--quiet"]) == 0
        outs[name] = (
            json.loads((tmp_path / name / "config.json").read_text()),
            json.loads((tmp_path / name / "metrics.json").read_text()),
        )
    assert outs["old"][0] == outs["new"][0]
    assert outs["old"][0]["classical"]["icp"]["motion_prior"] == "velocity"
    assert outs["old"][1]["ate"] == pytest.approx(outs["new"][1]["ate"], rel=1e-9)
    assert outs["old"][1]["ate"] < outs["old"][1]["initial_ate"]


def test_set_takes_an_old_key_and_warns_with_the_new_one(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """``--set`` alone is a request of no version (1): old keys are read. Over a saved config of
    version 2 they are refused by name: that format has no such key."""
    from strep_cli.main import build_config, make_parser

    sets = ["classical.icp_scales=[1.0]", "loss.loop_radius=0.25", "classical.kiss.prior=init"]
    args = make_parser().parse_args(["run", "x", *(arg for s in sets for arg in ("--set", s))])
    with caplog.at_level(logging.WARNING, logger="strep_core.config"):
        cfg = build_config(args)
    assert cfg.classical.icp.scales == [1.0]
    assert cfg.loss.loop_radius_fraction == 0.25 and cfg.classical.kiss.prior == "init"
    assert "classical.icp_scales -> classical.icp.scales" in caplog.text
    RunConfig(method="icp").save(tmp_path / "saved.json")
    args = make_parser().parse_args(["run", "x", "--config", str(tmp_path / "saved.json"), "--set", sets[0]])
    with pytest.raises(ConfigError, match=r"classical\.icp_scales: Extra inputs"):
        build_config(args)


@pytest.mark.parametrize(
    ("given", "error"),
    [
        ({"classical": {"icp_foo": 1}}, "classical.icp_foo: Extra inputs are not permitted"),
        ({"classical": {"icp": {"foo": 1}}}, "classical.icp.foo: Extra inputs are not permitted"),
        ({"loss": {"loop_radiuss": 1}}, "loss.loop_radiuss: Extra inputs are not permitted"),
        ({"classical": {"icp_yaw_axis": [0, 0, 0]}}, "classical.icp.yaw_axis: Value error, yaw_axis must be"),
        ({"classical": {"kiss_voxel": -1}}, "classical.kiss.voxel: Input should be greater than 0"),
    ],
)
def test_unknown_and_bad_keys_are_refused_by_name(given: dict[str, Any], error: str) -> None:
    with pytest.raises(ConfigError, match=error.replace(".", r"\.")):
        RunConfig.build(method="icp", **given)


def test_a_rest_job_body_with_old_keys_runs_under_the_new_names(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from app.core.config import Settings
    from app.main import create_app

    settings = Settings(data_dir=tmp_path / "service", max_concurrent_jobs=1, worker_threads=1)
    body = {
        "sequence_id": "sample:sim2d-small",
        "method": "icp",
        "frames": "0:6",
        "classical": {"icp_iterations": 7, "event_interval": 3},
        "loss": {"loop_radius": 0.4},
    }
    with TestClient(create_app(settings)) as client:
        r = client.post("/api/jobs", json=body)
        assert r.status_code == 201, r.text
        job = r.json()
        assert job["config"]["classical"]["icp"]["iterations"] == 7
        assert job["config"]["classical"]["event_interval_frames"] == 3
        assert job["config"]["loss"]["loop_radius_fraction"] == 0.4
        bad = client.post("/api/jobs", json={**body, "classical": {"icp_nonsense": 1}})
        assert bad.status_code == 422 and "classical.icp_nonsense" in bad.text
        deadline = time.monotonic() + 120
        while (status := client.get(f"/api/jobs/{job['id']}").json()["status"]) not in {"succeeded", "failed"}:
            assert time.monotonic() < deadline, status
            time.sleep(0.1)
        assert status == "succeeded"


def test_every_saved_config_of_a_benchmark_row_loads_again() -> None:
    """The bunny[identity] rows run every method from identity with the warm-start settings
    (start pose-graph, init identity); what they save must load and keep both."""
    from strep_core.resolve import resolve
    from strep_core.samples import load_sample

    asked = RunConfig(method="strep").model_copy(update={"init": "identity", "start": "pose-graph"})  # case_config
    saved = resolve(asked, load_sample("sim2d-small").select("0:12")).config
    again = RunConfig.model_validate(saved.model_dump(mode="json"))
    assert (again.start, again.init) == ("pose-graph", "identity")
    assert again.loss.robust == RunConfig(method="strep").loss.robust  # the warm start's loss, not scratch's
