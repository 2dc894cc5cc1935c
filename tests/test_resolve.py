"""One resolve stage (`strep_core.resolve`): the command line and the service run the same
resolved config on the same input, and ``config.json`` holds exactly what ran."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from strep_cli.main import main as cli
from strep_core.config import CONFIG_VERSION, RunConfig
from strep_core.profiles import START_OVERLAYS
from strep_core.resolve import resolve
from strep_core.samples import load_sample

FINAL = {"succeeded", "failed", "cancelled", "interrupted"}


def _wait(client: TestClient, job_id: str, timeout: float = 300) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while (job := client.get(f"/api/jobs/{job_id}").json())["status"] not in FINAL:
        assert time.monotonic() < deadline, job
        time.sleep(0.1)
    return job


def _cli(source: str, out: Path, *args: str) -> tuple[dict[str, Any], dict[str, Any]]:
    assert cli(["run", source, "--out", str(out), "--threads", "1", "--quiet", *args]) == 0
    return json.loads((out / "config.json").read_text()), json.loads((out / "metrics.json").read_text())


def _service(client: TestClient, sequence_id: str, body: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    r = client.post("/api/jobs", json={"sequence_id": sequence_id, **body})
    assert r.status_code == 201, r.text
    job = _wait(client, r.json()["id"])
    assert job["status"] == "succeeded", job
    saved = client.get(f"/api/jobs/{job['id']}/files/config.json").json()
    assert job["config"] == saved  # the job shows what ran once it has run
    return saved, job["metrics"]


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory):
    settings = Settings(data_dir=tmp_path_factory.mktemp("service"), max_concurrent_jobs=1, worker_threads=1)
    with TestClient(create_app(settings)) as c:
        yield c


def test_cli_and_service_run_the_same_strep_warm_start(client: TestClient, tmp_path: Path) -> None:
    """sample:sim2d-small strep: the service used to run the pose-graph warm start without the
    data's profile (laser-dense: no global scan matcher), 0.125 px where the command line gave 0.069."""
    cli_cfg, cli_m = _cli("sample:sim2d-small", tmp_path, "--method", "strep", "--frames", "0:24", "--iterations", "3")
    svc_cfg, svc_m = _service(
        client, "sample:sim2d-small", {"method": "strep", "frames": "0:24", "optim": {"iterations": 3}}
    )
    assert svc_cfg == cli_cfg
    assert cli_cfg["profile"] == "laser-dense" and cli_cfg["classical"]["scanmatch"]["consecutive"] == "off"
    assert (cli_cfg["init"], cli_cfg["start"], cli_cfg["config_version"]) == ("multiway", "pose-graph", CONFIG_VERSION)
    assert svc_m["ate"] == pytest.approx(cli_m["ate"], rel=1e-6)
    assert svc_m["initial_ate"] == pytest.approx(cli_m["initial_ate"], rel=1e-9)


@pytest.mark.slow
def test_cli_and_service_run_the_same_multiway_on_intel(client: TestClient, shared_data: Path, tmp_path: Path) -> None:
    """intel[0:100] multiway: the service gave 0.0733 m on the defaults, the command line 0.421 m
    with the probe's laser-keyframes profile; both now run the profile."""
    log = shared_data / "carmen" / "intel-corrected.log.gz"
    cli_cfg, cli_m = _cli(str(log), tmp_path, "--method", "multiway", "--frames", "0:100")
    with log.open("rb") as f:
        r = client.post("/api/sequences", files={"file": (log.name, f)})
    assert r.status_code == 201, r.text
    svc_cfg, svc_m = _service(client, r.json()["id"], {"method": "multiway", "frames": "0:100"})
    assert svc_cfg == cli_cfg
    assert cli_cfg["profile"] == "laser-keyframes"
    assert cli_cfg["classical"]["icp"]["degeneracy"] == 0.05 and cli_cfg["loss"]["weak_weight"] == 0.1
    assert svc_m["ate"] == pytest.approx(cli_m["ate"], rel=1e-9)


def test_a_full_dump_request_still_gets_the_profile_only_when_it_was_resolved() -> None:
    """A request keeps only the fields given; a resolved config is a fixed point."""
    seq = load_sample("sim2d-small").select("0:24")
    asked = RunConfig.build(method="icp")
    done = resolve(asked, seq).config
    assert done.classical.scanmatch.consecutive == "off"  # laser-dense
    assert resolve(done, seq).config == done  # resolving again changes nothing
    again = RunConfig.model_validate_json(done.model_dump_json())
    assert resolve(again, seq).config == done  # its config.json re-runs it
    sparse = RunConfig.model_validate_json(asked.model_dump_json(exclude_unset=True))
    assert resolve(sparse, seq).config == done  # how requests travel to the worker


def test_resolved_config_has_no_auto_left() -> None:
    seq = load_sample("sim2d-small").select("0:24")
    cfg = resolve(RunConfig.build(method="strep", device="auto"), seq).config
    dumped = json.dumps(cfg.model_dump(exclude={"classical": {"kiss": {"prior"}}}))
    assert '"auto"' not in dumped and cfg.device == "cpu" and cfg.threads >= 1
    c = cfg.classical
    s = seq.scale()
    assert c.icp.max_correspondence == pytest.approx(c.icp.correspondence_fraction * s)
    assert c.posegraph.loop_radius == pytest.approx(c.posegraph.loop_radius_fraction * s)
    scratch = resolve(RunConfig.build(method="strep", init="identity"), seq).config
    assert (scratch.start, scratch.init) == ("scratch", "identity")
    assert scratch.optim.lr_latent == START_OVERLAYS["scratch"]["optim"]["lr_latent"]  # the start's overlay
    kept = resolve(RunConfig.build(method="strep", init="identity", optim={"lr_latent": 0.003}), seq).config
    assert kept.optim.lr_latent == 0.003  # what was given wins


def test_an_unversioned_file_is_read_as_version_one() -> None:
    old = {"method": "icp", "classical": {"icp_scales": [1.0]}}
    assert RunConfig.model_validate(old).classical.icp.scales == [1.0]
    with pytest.raises(ValueError, match="icp_scales"):  # version 2 has no such key
        RunConfig.model_validate({**old, "config_version": 2})


def test_a_job_past_its_memory_budget_fails_and_the_service_runs_on(tmp_path: Path) -> None:
    """Issue 29: one job could take the machine's memory. Its worker is killed past the budget;
    the service answers and the next job runs."""
    settings = Settings(
        data_dir=tmp_path / "service",
        max_concurrent_jobs=2,
        worker_threads=1,
        job_memory_mib=700,
        plugins=["strep_demo_methods"],
    )
    with TestClient(create_app(settings)) as c:
        hog = c.post("/api/jobs", json={"sequence_id": "sample:sim2d-small", "method": "demo-hog", "frames": "0:6"})
        calm = c.post(
            "/api/jobs",
            json={
                "sequence_id": "sample:sim2d-small",
                "method": "demo-sleep",
                "frames": "0:6",
                "optim": {"iterations": 40},
            },
        )
        assert hog.status_code == calm.status_code == 201
        failed = _wait(c, hog.json()["id"], timeout=120)
        assert failed["status"] == "failed", failed
        assert "more than its memory budget of 700 MiB" in failed["error"]
        assert _wait(c, calm.json()["id"], timeout=120)["status"] == "succeeded"
        assert c.get("/api/health").status_code == 200
        after = c.post("/api/jobs", json={"sequence_id": "sample:sim2d-small", "method": "identity", "frames": "0:6"})
        assert _wait(c, after.json()["id"], timeout=120)["status"] == "succeeded"
