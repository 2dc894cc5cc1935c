"""The REST API through FastAPI's TestClient: sequences, jobs, events, files, cancel, crashes, queue.

Jobs run in real worker processes. The ``demo-*`` methods (``strep_demo_methods``, tests/plugins, enabled with the
``plugins`` setting) sleep instead of computing, so cancel, kill and queue tests are cheap
and do not depend on how fast the machine is.
"""

from __future__ import annotations

import asyncio
import io
import os
import signal
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import FINAL, parse_sse, wait_until

from app.core.config import InsecureSettings, Settings
from app.main import create_app
from app.server import serve
from app.services import DataDirBusy, Service
from app.services.broadcast import Mailbox
from app.store import StoredEvent
from strep_core.events import parse_event
from strep_core.io.npz import write_npz
from strep_core.methods import available
from strep_core.profiles import START_OVERLAYS

LONG = 100_000  # demo iterations: far longer than any test waits; such jobs are always cancelled


# ---- helpers ---------------------------------------------------------------------------------


def wait_job(client: TestClient, job_id: str, statuses: set[str], *, timeout: float = 120) -> dict[str, Any]:
    """Poll until the job's status is one of ``statuses`` (a guard against hangs, not a timing test)."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/api/jobs/{job_id}").json()
        if job["status"] in statuses:
            return job
        if time.monotonic() > deadline:
            raise AssertionError(f"job {job_id} still {job['status']} after {timeout} s: {job}")
        time.sleep(0.05)


def create_job(client: TestClient, sequence_id: str, method: str, **config: Any) -> dict[str, Any]:
    r = client.post("/api/jobs", json={"sequence_id": sequence_id, "method": method, **config})
    assert r.status_code == 201, r.text
    return r.json()


def running_worker(client: TestClient, job_id: str) -> int:
    """The pid of a running job's worker once it has emitted an iteration event (from the store)."""
    store = client.app.state.service.store  # type: ignore[attr-defined]

    def ready() -> int | None:
        job = store.get_job(job_id)
        # queued, running, stage load, start, then an iteration: the fifth event
        return job["pid"] if job["pid"] and job["last_event_id"] >= 5 else None

    return wait_until(ready, what=f"worker of {job_id}")


# ---- fixtures --------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def sim_npz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated 2D sequence with ground truth: 8 frames x 256 points, pixels."""
    from strep_core.sim.lidar2d import simulate_2d

    path = tmp_path_factory.mktemp("data") / "sim8.npz"
    write_npz(simulate_2d(3, frames=8), path)
    return path


def make_settings(data_dir: Path, **overrides: Any) -> Settings:
    values: dict[str, Any] = {
        "data_dir": data_dir,
        "plugins": ["strep_demo_methods"],
        "max_concurrent_jobs": 2,
        "cancel_grace_seconds": 1.0,
        "worker_threads": 1,
        **overrides,
    }
    return Settings(**values)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("service")


@pytest.fixture(scope="module")
def client(data_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(make_settings(data_dir))) as c:
        yield c


@pytest.fixture(scope="module")
def sequence(client: TestClient, sim_npz: Path) -> dict[str, Any]:
    with sim_npz.open("rb") as f:
        r = client.post("/api/sequences", files={"file": ("sim8.npz", f)})
    assert r.status_code == 201, r.text
    return r.json()


@pytest.fixture(autouse=True)
def no_leftover_jobs(request: pytest.FixtureRequest) -> Iterator[None]:
    """Every test leaves no job queued or running (the queue tests need free slots)."""
    yield
    if "client" not in request.fixturenames:
        return
    client: TestClient = request.getfixturevalue("client")
    for status in ("queued", "running"):
        for job in client.get("/api/jobs", params={"status": status}).json()["data"]:
            client.delete(f"/api/jobs/{job['id']}")
            wait_job(client, job["id"], FINAL)


# ---- service -----------------------------------------------------------------------------------


def test_health_lists_methods(client: TestClient) -> None:
    r = client.get("/api/health")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ok"
    assert body["max_concurrent_jobs"] == 2
    assert {"identity", "icp", "demo-sleep"} <= set(body["methods"])
    methods = client.get("/api/methods").json()
    assert methods["count"] == len(methods["data"]) == len(body["methods"])
    assert {m["name"]: m["learned"] for m in methods["data"]}["identity"] is False


def test_openapi_documents_the_api(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    assert {"/api/sequences", "/api/jobs", "/api/jobs/{job_id}/events", "/api/comparisons"} <= set(schema["paths"])
    upload = schema["paths"]["/api/sequences"]["post"]["requestBody"]["content"]["multipart/form-data"]
    assert upload["schema"]["required"] == ["file"]
    assert client.get("/docs").status_code == 200


# ---- sequences ---------------------------------------------------------------------------------


def test_upload_reads_and_stores_the_sequence(client: TestClient, sequence: dict[str, Any], data_dir: Path) -> None:
    assert sequence["id"].startswith("seq_")
    assert (sequence["frames"], sequence["dims"], sequence["points"]) == (8, 2, 8 * 256)
    assert sequence["has_ground_truth"] is True
    assert (sequence["unit"], sequence["format"], sequence["filename"]) == ("px", "npz", "sim8.npz")
    stored = data_dir / "uploads" / sequence["id"] / "sequence.npz"
    assert stored.stat().st_size == sequence["size_bytes"]
    assert client.get(f"/api/sequences/{sequence['id']}").json() == sequence
    listed = client.get("/api/sequences").json()
    assert sequence in listed["data"]
    assert listed["count"] == len(listed["data"])
    assert not any((data_dir / "uploads" / ".tmp").iterdir())


def test_upload_with_frame_selection_and_name(client: TestClient, sim_npz: Path) -> None:
    with sim_npz.open("rb") as f:
        r = client.post("/api/sequences", files={"file": ("x.npz", f)}, data={"frames": "0:6:2", "name": "every other"})
    assert r.status_code == 201, r.text
    body = r.json()
    assert (body["frames"], body["selection"], body["name"]) == (3, "0:6:2", "every other")
    assert client.delete(f"/api/sequences/{body['id']}").status_code == 204


def ply_zip(frames: int = 4, points: int = 60) -> bytes:
    """A .zip of ASCII PLY frames (3D) in a folder, with a TUM pose file."""
    rng = np.random.default_rng(2)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for i in range(frames):
            pts = rng.uniform(0, 2, size=(points, 3))
            header = f"ply\nformat ascii 1.0\nelement vertex {points}\n"
            header += "property float x\nproperty float y\nproperty float z\nend_header\n"
            zf.writestr(f"scans/scan_{i}.ply", header + "".join(f"{x} {y} {z}\n" for x, y, z in pts))
        zf.writestr("scans/poses.tum", "".join(f"{i} {0.1 * i} 0 0 0 0 0 1\n" for i in range(frames)))
    return buf.getvalue()


@pytest.mark.parametrize(
    ("filename", "frames", "expected"),
    [
        ("scans.zip", None, {"frames": 4, "dims": 3, "points": 240, "format": "zip", "has_ground_truth": True}),
        ("v1_pose0.tar", "::8", {"frames": 32, "dims": 2, "points": 32 * 256, "format": "deepmapping", "unit": "px"}),
        ("intel-corrected.log.gz", "0:50", {"frames": 50, "dims": 2, "format": "carmen", "unit": "m"}),
    ],
)
def test_upload_each_format(
    client: TestClient, shared_data: Path, filename: str, frames: str | None, expected: dict[str, Any]
) -> None:
    if filename.endswith(".zip"):
        content = ply_zip()
    else:
        folder = "deepmapping_2d" if filename.endswith(".tar") else "carmen"
        content = (shared_data / folder / filename).read_bytes()
    r = client.post("/api/sequences", files={"file": (filename, content)}, data={"frames": frames} if frames else {})
    assert r.status_code == 201, r.text
    body = r.json()
    assert {k: body[k] for k in expected} == expected
    assert body["size_bytes"] == len(content)
    assert client.delete(f"/api/sequences/{body['id']}").status_code == 204


def test_bundled_samples_are_listed_and_protected(client: TestClient) -> None:
    samples = [s for s in client.get("/api/sequences").json()["data"] if s["source"] == "sample"]
    if not samples:
        pytest.skip("no bundled samples")
    first = samples[0]
    assert first["id"] == f"sample:{first['name']}"
    assert client.get(f"/api/sequences/{first['id']}").json() == first
    r = client.delete(f"/api/sequences/{first['id']}")
    assert r.status_code == 409
    assert "bundled" in r.json()["detail"]


def test_delete_sequence(client: TestClient, sim_npz: Path, data_dir: Path) -> None:
    with sim_npz.open("rb") as f:
        seq = client.post("/api/sequences", files={"file": ("del.npz", f)}).json()
    job = create_job(client, seq["id"], "demo-sleep", optim={"iterations": LONG})
    r = client.delete(f"/api/sequences/{seq['id']}")
    assert r.status_code == 409
    assert "queued or running jobs" in r.json()["detail"]
    client.delete(f"/api/jobs/{job['id']}")
    wait_job(client, job["id"], FINAL)
    assert client.delete(f"/api/sequences/{seq['id']}").status_code == 204
    assert client.get(f"/api/sequences/{seq['id']}").status_code == 404
    assert not (data_dir / "uploads" / seq["id"]).exists()
    assert client.get(f"/api/jobs/{job['id']}").status_code == 200  # finished jobs outlive their input


# ---- jobs, events and files ------------------------------------------------------------------


def test_identity_job_events_and_files(client: TestClient, sequence: dict[str, Any]) -> None:
    job = create_job(client, sequence["id"], "identity")
    # the answer is read after the supervisor was woken: the job may already have started
    assert job["status"] in ("queued", "running")
    assert (job["method"], job["sequence_id"]) == ("identity", sequence["id"])
    assert job["config"]["method"] == "identity"

    r = client.get(f"/api/jobs/{job['id']}/events")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/event-stream")
    events = parse_sse(r.text)
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))
    kinds = [e["event"] for e in events]
    # stages: load (the worker reads the sequence), then write (the result files) after the result
    assert kinds == ["status", "status", "stage", "start", "result", "stage", "status"]
    assert [e["data"]["stage"] for e in events if e["event"] == "stage"] == ["load", "write"]
    assert [e["data"]["status"] for e in events if e["event"] == "status"] == ["queued", "running", "succeeded"]
    for e in events:
        assert e["data"]["kind"] == e["event"]
        if e["event"] != "status":
            assert parse_event(e["data"]).kind == e["event"]
    result = next(e["data"] for e in events if e["event"] == "result")
    assert len(result["poses"]) == 8

    done = client.get(f"/api/jobs/{job['id']}").json()
    assert done["status"] == "succeeded"
    assert done["error"] is None
    assert done["last_event_id"] == len(events)
    assert done["metrics"]["ate"] == pytest.approx(result["metrics"]["ate"])
    assert done["metrics"]["ate"] > 1.0  # identity is far from the truth on a moving sensor
    assert set(done["files"]) == {"trajectory.tum", "map.ply", "metrics.json", "config.json", "recording.rrd"}

    tum = client.get(f"/api/jobs/{job['id']}/files/trajectory.tum")
    assert tum.status_code == 200
    rows = [line.split() for line in tum.text.splitlines() if line and not line.startswith("#")]
    assert len(rows) == 8 and all(len(row) == 8 for row in rows)
    metrics = client.get(f"/api/jobs/{job['id']}/files/metrics.json").json()
    assert metrics["ate"] == pytest.approx(done["metrics"]["ate"])
    config = client.get(f"/api/jobs/{job['id']}/files/config.json").json()
    assert config["method"] == "identity"
    ply = client.get(f"/api/jobs/{job['id']}/files/map.ply")
    assert ply.content.startswith(b"ply")
    assert b"element vertex 2048" in ply.content[:500]

    missing = client.get(f"/api/jobs/{job['id']}/files/model.pt")
    assert missing.status_code == 404
    assert "model.pt" in missing.json()["detail"]
    for bad in ("strep.db", "...", "passwd"):
        r = client.get(f"/api/jobs/{job['id']}/files/{bad}")
        assert r.status_code == 404
        assert "no result file named" in r.json()["detail"]
    assert client.get(f"/api/jobs/{job['id']}/files/..%2F..%2Fstrep.db").status_code == 404


def test_icp_beats_identity(client: TestClient, sequence: dict[str, Any]) -> None:
    job = create_job(client, sequence["id"], "icp")
    done = wait_job(client, job["id"], FINAL)
    assert done["status"] == "succeeded", done
    assert done["metrics"]["ate"] < 0.5 * done["metrics"]["initial_ate"]
    events = parse_sse(client.get(f"/api/jobs/{job['id']}/events").text)
    iterations = [e["data"] for e in events if e["event"] == "iteration"]
    assert iterations and iterations[-1]["iteration"] == iterations[-1]["total"] == 8


def test_events_resume_after_last_event_id(client: TestClient, sequence: dict[str, Any]) -> None:
    job = create_job(client, sequence["id"], "demo-sleep", optim={"iterations": 20, "event_interval": 5})
    wait_job(client, job["id"], FINAL)
    full = parse_sse(client.get(f"/api/jobs/{job['id']}/events").text)
    assert [e["data"]["iteration"] for e in full if e["event"] == "iteration"] == [5, 10, 15, 20]
    resumed = parse_sse(client.get(f"/api/jobs/{job['id']}/events", headers={"Last-Event-ID": "3"}).text)
    assert resumed == full[3:]
    assert parse_sse(client.get(f"/api/jobs/{job['id']}/events", params={"after": 5}).text) == full[5:]
    assert client.get(f"/api/jobs/{job['id']}/events", headers={"Last-Event-ID": "999"}).text == ""
    bad = client.get(f"/api/jobs/{job['id']}/events", headers={"Last-Event-ID": "three"})
    assert bad.status_code == 400
    assert "Last-Event-ID" in bad.json()["detail"]


def test_list_jobs_filters_and_pages(client: TestClient, sequence: dict[str, Any]) -> None:
    jobs = [create_job(client, sequence["id"], "identity") for _ in range(3)]
    for job in jobs:
        wait_job(client, job["id"], FINAL)
    page = client.get("/api/jobs", params={"sequence_id": sequence["id"], "limit": 2}).json()
    assert len(page["data"]) == 2
    assert page["count"] >= 3
    assert page["data"][0]["id"] == jobs[-1]["id"]  # newest first
    nxt = client.get("/api/jobs", params={"sequence_id": sequence["id"], "limit": 2, "offset": 1}).json()
    assert nxt["data"][0]["id"] == jobs[-2]["id"]
    succeeded = client.get("/api/jobs", params={"status": "succeeded", "limit": 1000}).json()
    assert {j["id"] for j in jobs} <= {j["id"] for j in succeeded["data"]}
    assert all(j["status"] == "succeeded" for j in succeeded["data"])


def test_comparison_runs_one_job_per_method(client: TestClient, sequence: dict[str, Any]) -> None:
    r = client.post(
        "/api/comparisons",
        json={"sequence_id": sequence["id"], "methods": ["identity", "icp"], "config": {"seed": 3}},
    )
    assert r.status_code == 201, r.text
    comparison = r.json()
    assert comparison["methods"] == ["identity", "icp"]
    assert [j["method"] for j in comparison["jobs"]] == ["identity", "icp"]
    assert {j["comparison_id"] for j in comparison["jobs"]} == {comparison["id"]}
    assert all(j["config"]["seed"] == 3 for j in comparison["jobs"])
    for job in comparison["jobs"]:
        wait_job(client, job["id"], FINAL)
    done = client.get(f"/api/comparisons/{comparison['id']}").json()
    assert done["status"] == "succeeded"
    ate = {j["method"]: j["metrics"]["ate"] for j in done["jobs"]}
    assert ate["icp"] < ate["identity"]
    listed = client.get("/api/jobs", params={"comparison_id": comparison["id"]}).json()
    assert listed["count"] == 2


def test_comparison_defaults_to_strep_and_strep_nolink(client: TestClient, sequence: dict[str, Any]) -> None:
    methods = available()
    r = client.post("/api/comparisons", json={"sequence_id": sequence["id"], "config": {"optim": {"iterations": 2}}})
    if "strep" in methods and "strep-nolink" in methods:
        assert r.status_code == 201, r.text
        assert r.json()["methods"] == ["strep", "strep-nolink"]
        for job in r.json()["jobs"]:
            client.delete(f"/api/jobs/{job['id']}")
    else:
        assert r.status_code == 422
        assert "unknown method 'strep" in r.json()["detail"]


def test_strep_job_with_few_iterations(client: TestClient) -> None:
    if "strep" not in available():
        pytest.skip("the strep method is not registered yet")
    job = create_job(
        client,
        "sample:sim2d-small",
        "strep",
        frames="0:12",
        init="identity",
        optim={"iterations": 4, "event_interval": 2},
    )
    done = wait_job(client, job["id"], FINAL, timeout=300)
    assert done["status"] == "succeeded", done
    assert np.isfinite(done["metrics"]["ate"])
    assert "model.pt" in done["files"]
    model = client.get(f"/api/jobs/{job['id']}/files/model.pt")
    assert model.status_code == 200 and len(model.content) > 1000
    events = parse_sse(client.get(f"/api/jobs/{job['id']}/events").text)
    assert [e["data"]["iteration"] for e in events if e["event"] == "iteration"][-1] == 4


def test_start_setting_round_trips(client: TestClient) -> None:
    """A job stores its request (the fields given); once run, it shows the resolved config."""
    job = create_job(client, "sample:sim2d-small", "strep", frames="0:12", start="scratch", optim={"iterations": 3})
    assert job["config"]["start"] == "scratch" and job["config"]["optim"] == {"iterations": 3}
    done = wait_job(client, job["id"], FINAL, timeout=300)
    assert done["status"] == "succeeded", done
    assert (done["config"]["start"], done["config"]["init"]) == ("scratch", "identity")
    assert done["config"]["optim"]["iterations"] == 3  # given: kept
    assert done["config"]["optim"]["lr_latent"] == START_OVERLAYS["scratch"]["optim"]["lr_latent"]  # the start's
    assert done["config"] == client.get(f"/api/jobs/{job['id']}/files/config.json").json()
    assert done["metrics"]["initial_guess"] == "identity"
    events = parse_sse(client.get(f"/api/jobs/{job['id']}/events").text)
    its = [e["data"] for e in events if e["event"] == "iteration"]
    assert its[0]["iteration"] == 0 and its[0]["ate"] == pytest.approx(done["metrics"]["initial_ate"], rel=1e-6)
    warm = wait_job(client, create_job(client, "sample:sim2d-small", "identity", frames="0:12")["id"], FINAL)
    assert (warm["config"]["start"], warm["config"]["optim"]["lr_latent"]) == ("pose-graph", 1e-4)
    body = {"sequence_id": "sample:sim2d-small", "config": {"start": "scratch", "init": "multiway"}}
    r = client.post("/api/comparisons", json=body)
    assert r.status_code == 422 and "start" in r.text, r.text


# ---- cancel, crash, queue ------------------------------------------------------------------------


def test_cancel_queued_and_running_jobs(client: TestClient, sequence: dict[str, Any]) -> None:
    running = [create_job(client, sequence["id"], "demo-sleep", optim={"iterations": LONG}) for _ in range(2)]
    queued = create_job(client, sequence["id"], "demo-sleep", optim={"iterations": LONG})
    for job in running:
        running_worker(client, job["id"])
    assert client.get(f"/api/jobs/{queued['id']}").json()["status"] == "queued"

    r = client.delete(f"/api/jobs/{queued['id']}")
    assert r.status_code == 200
    assert (r.json()["status"], r.json()["error"]) == ("cancelled", "cancelled before it started")
    assert client.delete(f"/api/jobs/{queued['id']}").status_code == 200  # idempotent

    for job in running:
        r = client.delete(f"/api/jobs/{job['id']}")
        assert r.status_code == 202
        assert r.json()["cancel_requested"] is True
    for job in running:
        done = wait_job(client, job["id"], FINAL)
        assert done["status"] == "cancelled"
        assert "cancelled" in done["error"]
        assert done["files"] == []
        events = parse_sse(client.get(f"/api/jobs/{job['id']}/events").text)
        assert events[-1]["data"]["status"] == "cancelled"
        assert any(e["event"] == "iteration" for e in events)
    never = parse_sse(client.get(f"/api/jobs/{queued['id']}/events").text)
    assert [e["data"]["status"] for e in never] == ["queued", "cancelled"]
    r = client.get(f"/api/jobs/{queued['id']}/files/trajectory.tum")
    assert r.status_code == 404


def test_cancel_terminates_a_worker_that_ignores_it(client: TestClient, sequence: dict[str, Any]) -> None:
    job = create_job(client, sequence["id"], "demo-stubborn", optim={"iterations": LONG})
    running_worker(client, job["id"])
    assert client.delete(f"/api/jobs/{job['id']}").status_code == 202
    done = wait_job(client, job["id"], FINAL)
    assert done["status"] == "cancelled"
    assert "did not stop within 1 s and was terminated" in done["error"]
    assert done["exit_code"] == -signal.SIGTERM


def test_finished_job_cannot_be_cancelled(client: TestClient, sequence: dict[str, Any]) -> None:
    job = create_job(client, sequence["id"], "identity")
    wait_job(client, job["id"], FINAL)
    r = client.delete(f"/api/jobs/{job['id']}")
    assert r.status_code == 409
    assert "already finished (succeeded)" in r.json()["detail"]


def test_killed_worker_fails_only_its_job(client: TestClient, sequence: dict[str, Any]) -> None:
    victim = create_job(client, sequence["id"], "demo-sleep", optim={"iterations": LONG})
    survivor = create_job(client, sequence["id"], "demo-sleep", optim={"iterations": 100, "event_interval": 10})
    pid = running_worker(client, victim["id"])
    os.kill(pid, signal.SIGKILL)
    failed = wait_job(client, victim["id"], FINAL)
    assert failed["status"] == "failed"
    assert failed["error"] == "the worker process was killed by signal SIGKILL before it reported a result"
    assert failed["exit_code"] == -signal.SIGKILL
    events = parse_sse(client.get(f"/api/jobs/{victim['id']}/events").text)
    assert events[-1]["data"] == {"kind": "status", "status": "failed", "error": failed["error"], "exit_code": -9}
    ok = wait_job(client, survivor["id"], FINAL)
    assert ok["status"] == "succeeded", ok
    assert client.get("/api/health").json()["status"] == "ok"


def test_queue_runs_at_most_two_jobs_in_order(client: TestClient, sequence: dict[str, Any]) -> None:
    jobs = [create_job(client, sequence["id"], "demo-sleep", optim={"iterations": 40}) for _ in range(3)]
    done = [wait_job(client, job["id"], FINAL) for job in jobs]
    assert [d["status"] for d in done] == ["succeeded"] * 3
    first, second, third = done
    assert first["started_at"] <= second["started_at"] <= third["started_at"]
    assert third["started_at"] >= min(first["finished_at"], second["finished_at"])


# ---- settings and security -------------------------------------------------------------------


def test_token_is_required_when_set(tmp_path: Path) -> None:
    with TestClient(create_app(make_settings(tmp_path, api_token="s3cret"))) as c:
        r = c.get("/api/health")
        assert r.status_code == 401
        assert r.json() == {"detail": "missing or invalid bearer token"}
        assert r.headers["www-authenticate"] == "Bearer"
        assert c.get("/api/jobs", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert c.get("/api/jobs", headers={"Authorization": "Basic s3cret"}).status_code == 401
        assert c.get("/api/jobs", headers={"Authorization": "Bearer s3cret"}).status_code == 200


def test_cors_only_when_configured(tmp_path: Path) -> None:
    origin = {"Origin": "http://example.org"}
    with TestClient(create_app(make_settings(tmp_path / "a"))) as c:
        assert "access-control-allow-origin" not in c.get("/api/health", headers=origin).headers
    with TestClient(create_app(make_settings(tmp_path / "b", cors_origins="http://example.org"))) as c:
        assert c.get("/api/health", headers=origin).headers["access-control-allow-origin"] == "http://example.org"
        other = c.get("/api/health", headers={"Origin": "http://evil.example"})
        assert "access-control-allow-origin" not in other.headers


def test_refuses_to_serve_beyond_loopback_without_token(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert Settings().host == "127.0.0.1"
    for host in ("127.0.0.1", "::1", "localhost"):
        Settings(host=host).check_secure()
    with pytest.raises(InsecureSettings, match="STREP_API_TOKEN"):
        Settings(host="0.0.0.0").check_secure()
    Settings(host="0.0.0.0", api_token="t").check_secure()
    assert serve(host="0.0.0.0", port=1, data_dir=tmp_path) == 2
    assert "refusing to listen on 0.0.0.0" in capsys.readouterr().err


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("STREP_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("STREP_MAX_CONCURRENT_JOBS", "3")
    monkeypatch.setenv("STREP_CORS_ORIGINS", "http://a.test, http://b.test")
    monkeypatch.setenv("STREP_API_TOKEN", "")
    s = Settings()
    assert (s.data_dir, s.max_concurrent_jobs, s.api_token) == (tmp_path, 3, None)
    assert s.cors_origins == ["http://a.test", "http://b.test"]
    assert (s.port, s.viewer_port) == (8000, 8080)


def test_one_service_per_data_dir(data_dir: Path, client: TestClient) -> None:
    with pytest.raises(DataDirBusy, match="another STREP service"):
        Service(make_settings(data_dir))


# ---- event fan-out -----------------------------------------------------------------------------


def test_slow_subscriber_keeps_only_the_latest_iterations() -> None:
    async def scenario() -> list[StoredEvent]:
        box = Mailbox(asyncio.get_running_loop(), "job", limit=8)
        events = [StoredEvent("job", i, "iteration", "{}", 0.0) for i in range(1, 101)]
        events.insert(50, StoredEvent("job", 1000, "stage", "{}", 0.0))
        box.push(events)
        box.push([StoredEvent("job", 101, "status", "{}", 0.0)])
        got = await box.get(timeout=1.0)
        assert got is not None
        assert await box.get(timeout=0.01) == []
        box.close()
        assert await box.get(timeout=1.0) is None
        return got

    got = asyncio.run(scenario())
    assert [(e.kind, e.id) for e in got] == [("stage", 1000), ("iteration", 100), ("status", 101)]


def test_comparison_workers_exit_by_themselves(client: TestClient) -> None:
    """Each worker of a comparison exits on its own after its last message (exit code 0), not
    killed by the service's reaper (-9)."""
    body = {"sequence_id": "sample:sim2d-small", "config": {"frames": "0:12", "optim": {"iterations": 3}}}
    r = client.post("/api/comparisons", json={**body, "methods": ["strep", "strep-nolink"]})
    assert r.status_code == 201, r.text
    for job in r.json()["jobs"]:
        wait_job(client, job["id"], FINAL)
        deadline = time.monotonic() + 90  # a guard against hangs: the reaper kills after 30 s
        while (done := client.get(f"/api/jobs/{job['id']}").json()).get("exit_code") is None:
            assert time.monotonic() < deadline, done
            time.sleep(0.05)
        assert done["status"] == "succeeded", done
        assert done["exit_code"] == 0, done
