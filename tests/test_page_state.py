"""What the page is sent: typed run-state snapshots of jobs (``/api/jobs/{id}/state``) and the
starts with their default budgets (``/api/starts``), both worked out by the server."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from helpers import FINAL, parse_sse, wait_until

from app.core.config import Settings
from app.main import create_app
from strep_core.config import RunConfig

STATIC = Path(__file__).resolve().parents[1] / "static"


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    settings = Settings(data_dir=tmp_path_factory.mktemp("page"), worker_threads=1, max_concurrent_jobs=2)
    with TestClient(create_app(settings)) as c:
        yield c


def test_the_starts_and_their_budgets_come_from_the_run_config(client: TestClient) -> None:
    body = client.get("/api/starts").json()
    assert [s["name"] for s in body["data"]] == ["scratch", "pose-graph"] and body["default"] == "scratch"
    from strep_core.profiles import START_OVERLAYS

    for s in body["data"]:  # the start's overlay over the defaults, as the resolve stage applies it
        overlay = START_OVERLAYS[s["name"]].get("optim", {})
        assert s["iterations"] == overlay.get("iterations", RunConfig.build(method="strep").optim.iterations)
    assert [s["iterations"] for s in body["data"]] == [1000, 300]
    # labels short enough for the page's narrow column (before: "from scratch (the paper's setting" cut)
    assert all(len(s["label"]) <= 24 for s in body["data"])


def test_the_preset_is_the_services(client: TestClient) -> None:
    body = client.get("/api/preset").json()
    assert body == {"sequence_id": "sample:sim2d", "methods": ["strep", "strep-nolink"], "start": "scratch"}


def test_the_page_holds_no_copy_of_the_servers_names() -> None:
    """No rules language, no stage names, result file names, default budgets or preset in the page."""
    text = "\n".join(p.read_text() for p in [*sorted(STATIC.rglob("*.js")), STATIC / "index.html"])
    names = ("applyRules", "events/rules", "init:", "warm start", "recording.rrd", "metrics.json", "sample:")
    names += ('"strep"', '"strep-nolink"')  # the preset's methods
    for name in names:
        assert name not in text, name
    assert not re.search(r"\b(1000|300)\b", text)  # the starts' default iterations
    assert "data-iterations" not in text


def test_an_icp_job_streams_its_state_in_frames(client: TestClient) -> None:
    job = client.post("/api/jobs", json={"sequence_id": "sample:sim2d-small", "method": "icp"}).json()
    wait_until(lambda: client.get(f"/api/jobs/{job['id']}").json()["status"] in FINAL, timeout=120, what="icp")
    # a page that opens (or reloads) after the end gets the whole run in the stream
    states = [m["data"] for m in parse_sse(client.get(f"/api/jobs/{job['id']}/state").text)]
    last = states[-1]
    assert last["status"] == "succeeded" and {"metrics.json", "trajectory.tum"} <= set(last["files"])
    run = last["run"]
    assert (run["axis"], run["learned"], run["total"], run["progress"]) == ("frames", False, 64, "64 / 64 frames")
    assert run["loss"] == [] and len(run["ate"]) >= 6 and max(x for x, _ in run["ate"]) <= 64
    metrics = client.get(f"/api/jobs/{job['id']}").json()["metrics"]
    assert run["ate_end"] == [64, pytest.approx(metrics["ate"])]
    assert run["ate_start"] == [0, pytest.approx(metrics["initial_ate"])]
    assert run["stage_text"].startswith("done in ") and "64 frames, ATE 56 → 0.333 px" in run["stage_text"]
