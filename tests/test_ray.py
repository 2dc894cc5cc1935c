"""The ``ray`` executor end to end: a local Ray runtime (2 CPUs), the service with
``STREP_EXECUTOR=ray``, jobs on the bundled sample streamed, stored, cancelled and killed,
and ``strep bench --executor ray``.

Ray is an optional extra (``pip install 'strep-studio[ray]'``); CI installs it. Each job is a
Ray actor of one CPU (``worker_threads=1``), so the two job slots fill the runtime.
"""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import FINAL, parse_sse, wait_until

from app.core.config import RAY_MISSING, Settings
from app.main import create_app
from app.services.executors import LocalExecutor, RayExecutor, forwarded_env, ray_resources

ray = pytest.importorskip("ray")

# generous: a Ray worker imports torch and Open3D in a fresh process, minutes on a loaded
# machine (two CPU-bound runs beside the suite on 2 cores took past 60 s); idle it is seconds
pytestmark = pytest.mark.timeout(420)

LONG = 100_000  # iterations no test waits for: such jobs are always cancelled or killed


# ---- helpers ----------------------------------------------------------------


def wait_job(client: TestClient, job_id: str, *, timeout: float = 180) -> dict[str, Any]:
    def final() -> dict[str, Any] | None:
        job = client.get(f"/api/jobs/{job_id}").json()
        return job if job["status"] in FINAL else None

    return wait_until(final, timeout=timeout, what=f"job {job_id} to finish")


def create_job(client: TestClient, sequence_id: str, method: str, **config: Any) -> dict[str, Any]:
    r = client.post("/api/jobs", json={"sequence_id": sequence_id, "method": method, **config})
    assert r.status_code == 201, r.text
    return r.json()


def started_worker(client: TestClient, job_id: str) -> int:
    """The pid of a job's Ray worker once the job has emitted an iteration event."""
    store = client.app.state.service.store  # type: ignore[attr-defined]

    def ready() -> int | None:
        job = store.get_job(job_id)
        iterated = any(e.kind == "iteration" for e in store.events_after(job_id, 0))
        return job["pid"] if job["pid"] and iterated else None

    return wait_until(ready, timeout=180, what=f"an iteration of {job_id}")


# ---- fixtures ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ray_runtime() -> Iterator[None]:
    """A local Ray runtime of 2 CPUs for this module (the service uses it, and so does the bench)."""
    if ray.is_initialized():
        ray.shutdown()
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def client(ray_runtime: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data_dir = tmp_path_factory.mktemp("ray-service")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("STREP_EXECUTOR", "ray")
        mp.setenv("STREP_RAY_ADDRESS", "local")
        settings = Settings(
            data_dir=data_dir,
            plugins=["strep_demo_methods"],
            max_concurrent_jobs=2,
            cancel_grace_seconds=1.0,
            worker_threads=1,
        )
    assert settings.executor == "ray"
    with TestClient(create_app(settings)) as c:
        assert isinstance(c.app.state.service.jobs.executor, RayExecutor)  # type: ignore[attr-defined]
        yield c


# ---- settings ------------------------------------------------------------------------------------


def test_executor_settings(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    assert (Settings(data_dir=tmp_path).executor, Settings(data_dir=tmp_path).ray_address) == ("local", "local")
    monkeypatch.setenv("STREP_EXECUTOR", "ray")
    monkeypatch.setenv("STREP_RAY_ADDRESS", "auto")
    monkeypatch.setenv("STREP_RAY_NUM_CPUS", "3")
    s = Settings(data_dir=tmp_path)
    assert (s.executor, s.ray_address, s.ray_num_cpus) == ("ray", "auto", 3)
    monkeypatch.setenv("STREP_EXECUTOR", "slurm")
    with pytest.raises(ValueError, match="local"):
        Settings(data_dir=tmp_path)


def test_ray_executor_needs_ray_installed(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    with pytest.raises(ValueError, match=r"pip install 'strep-studio\[ray\]'"):
        Settings(data_dir=tmp_path, executor="ray")
    assert "strep-studio[ray]" in RAY_MISSING
    assert Settings(data_dir=tmp_path).executor == "local"  # the default install does not need Ray


def test_ray_resources_follow_the_job() -> None:
    assert ray_resources("cpu", 3) == {"num_cpus": 3.0, "num_gpus": 0.0}
    assert ray_resources("cuda", 1) == {"num_cpus": 1.0, "num_gpus": 1.0}
    assert ray_resources("auto", 2) == {"num_cpus": 2.0, "num_gpus": 0.0}


def test_ray_workers_get_the_service_environment_but_not_its_token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("STREP_SAMPLES_DIR", "/somewhere/samples")
    monkeypatch.setenv("STREP_API_TOKEN", "secret")
    env = forwarded_env()
    assert env["STREP_SAMPLES_DIR"] == "/somewhere/samples"
    assert "STREP_API_TOKEN" not in env
    assert all(k.startswith("STREP_") for k in env)


def test_local_executor_is_the_default(tmp_path: Path) -> None:
    import multiprocessing

    from app.services.executors import make_executor

    assert isinstance(make_executor(Settings(data_dir=tmp_path), multiprocessing.get_context("spawn")), LocalExecutor)


def test_service_starts_and_stops_its_own_ray_runtime(tmp_path: Path) -> None:
    """``ray_address=local`` and no Ray in the process: the service starts a runtime, then shuts it down."""
    if ray.is_initialized():
        pytest.skip("a Ray runtime is already up in this process")
    settings = Settings(
        data_dir=tmp_path,
        executor="ray",
        ray_address="local",
        ray_num_cpus=1,
        worker_threads=1,
        plugins=["strep_demo_methods"],
    )
    with TestClient(create_app(settings)) as c:
        assert ray.is_initialized()
        assert ray.cluster_resources()["CPU"] == 1
        job = wait_job(c, create_job(c, "sample:sim2d-small", "identity", frames="0:8")["id"])
        assert job["status"] == "succeeded", job
        assert "trajectory.tum" in job["files"]
        running = create_job(c, "sample:sim2d-small", "demo-sleep", optim={"iterations": LONG})
        started_worker(c, running["id"])
    assert not ray.is_initialized()
    # the job still running when the service stopped: interrupted, as with local workers
    from app.store import Store

    store = Store(settings.db_path)
    try:
        stopped = store.get_job(running["id"])
        assert stopped is not None
        assert stopped["status"] == "interrupted"
        assert stopped["error"] == "the service shut down while this job was running"
    finally:
        store.close()


# ---- jobs on Ray ---------------------------------------------------------------------------------


def test_two_jobs_stream_store_and_cancel(client: TestClient) -> None:
    """ICP runs to the end; a long STREP run is cancelled while it optimises (both on Ray)."""
    done_job = create_job(client, "sample:sim2d-small", "icp", frames="0:16")
    cancelled_job = create_job(
        client,
        "sample:sim2d-small",
        "strep",
        frames="0:12",
        init="identity",
        optim={"iterations": 5000, "event_interval": 1},
    )
    started_worker(client, cancelled_job["id"])
    r = client.delete(f"/api/jobs/{cancelled_job['id']}")
    assert r.status_code == 202, r.text
    assert r.json()["cancel_requested"] is True

    # the finished job: events in order, result stored, files served
    r = client.get(f"/api/jobs/{done_job['id']}/events")  # streams until the job ends
    assert r.headers["content-type"].startswith("text/event-stream")
    events = parse_sse(r.text)
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))
    kinds = [e["event"] for e in events]
    assert kinds[:4] == ["status", "status", "stage", "start"] and kinds[-3:] == ["result", "stage", "status"]
    assert [e["data"]["status"] for e in events if e["event"] == "status"] == ["queued", "running", "succeeded"]
    iterations = [e["data"]["iteration"] for e in events if e["event"] == "iteration"]
    assert iterations == sorted(iterations) and iterations[-1] == 16
    done = client.get(f"/api/jobs/{done_job['id']}").json()
    assert done["status"] == "succeeded", done
    assert done["last_event_id"] == len(events)
    assert np.isfinite(done["metrics"]["ate"])
    assert done["metrics"]["ate"] < done["metrics"]["initial_ate"]
    assert {"trajectory.tum", "map.ply", "metrics.json", "config.json"} <= set(done["files"])
    stored = client.app.state.service.store.get_job(done_job["id"])  # type: ignore[attr-defined]
    assert stored["pid"] and stored["pid"] != os.getpid()  # the Ray worker's process
    metrics = client.get(f"/api/jobs/{done_job['id']}/files/metrics.json")
    assert metrics.status_code == 200 and metrics.json()["ate"] == pytest.approx(done["metrics"]["ate"])
    tum = client.get(f"/api/jobs/{done_job['id']}/files/trajectory.tum")
    assert len([line for line in tum.text.splitlines() if line and not line.startswith("#")]) == 16
    assert client.get(f"/api/jobs/{done_job['id']}/files/map.ply").content.startswith(b"ply")

    # the cancelled job: stopped between iterations, no files
    stopped = wait_job(client, cancelled_job["id"])
    assert stopped["status"] == "cancelled", stopped
    assert stopped["error"] == "the run was cancelled"  # its own flag, not a kill
    assert stopped["files"] == []
    events = parse_sse(client.get(f"/api/jobs/{cancelled_job['id']}/events").text)
    assert [e["id"] for e in events] == list(range(1, len(events) + 1))
    assert any(e["event"] == "iteration" for e in events)
    assert events[-1]["data"]["status"] == "cancelled"
    assert client.get(f"/api/jobs/{cancelled_job['id']}/files/trajectory.tum").status_code == 404


def test_dead_ray_worker_fails_its_job(client: TestClient) -> None:
    victim = create_job(client, "sample:sim2d-small", "demo-sleep", optim={"iterations": LONG})
    pid = started_worker(client, victim["id"])
    os.kill(pid, signal.SIGKILL)
    failed = wait_job(client, victim["id"])
    assert failed["status"] == "failed"
    assert failed["error"].startswith("the Ray worker died before it reported a result: "), failed["error"]
    events = parse_sse(client.get(f"/api/jobs/{victim['id']}/events").text)
    assert events[-1]["data"]["status"] == "failed"


def test_cancel_kills_a_ray_worker_that_ignores_it(client: TestClient) -> None:
    job = create_job(client, "sample:sim2d-small", "demo-stubborn", optim={"iterations": LONG})
    started_worker(client, job["id"])
    assert client.delete(f"/api/jobs/{job['id']}").status_code == 202
    done = wait_job(client, job["id"])
    assert done["status"] == "cancelled"
    assert "did not stop within 1 s and was terminated" in done["error"]
    assert done["exit_code"] == -signal.SIGTERM
    # both slots are free again: a short job still runs
    ok = wait_job(client, create_job(client, "sample:sim2d-small", "identity", frames="0:8")["id"])
    assert ok["status"] == "succeeded", ok


# ---- strep bench --executor ray ------------------------------------------------------------------


def test_bench_spreads_runs_over_ray(ray_runtime: None, tmp_path: Path, shared_data: Path) -> None:
    from strep_cli import main

    code = main(
        [
            "bench",
            "--executor",
            "ray",
            "--suites",
            "v1_pose0",
            "--methods",
            "identity,icp",
            "--quick",
            "--data",
            str(shared_data),
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 0
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["executor"] == "ray"
    rows = {r["method"]: r for r in report["rows"]}
    assert [r["method"] for r in report["rows"]] == ["identity", "icp"]
    assert all(r["status"] == "ok" and r["case"] == "v1_pose0" for r in rows.values())
    assert rows["icp"]["ate"] < rows["identity"]["ate"]
    assert "| v1_pose0 | v1_pose0 |" in (tmp_path / "bench.md").read_text()


def test_bench_reports_a_dead_ray_task_as_a_failed_run(ray_runtime: None) -> None:
    from strep_bench.cases import BenchCase
    from strep_bench.ray_runner import run_cases_ray

    # nested functions: Ray ships them by value (this test module is not importable by its workers)
    def die() -> Any:
        os._exit(3)  # the Ray worker running this task dies

    def sample() -> Any:
        from strep_core.runner import load_input

        return load_input("sample:sim2d-small", frames="0:8")

    cases = [BenchCase("tiny", "crash", die), BenchCase("tiny", "sim2d-small[0:8]", sample)]
    rows = run_cases_ray(cases, ["identity"], quick=True)
    assert [(r["case"], r["method"]) for r in rows] == [("crash", "identity"), ("sim2d-small[0:8]", "identity")]
    assert rows[0]["status"].startswith("failed: WorkerCrashedError"), rows[0]["status"]
    assert rows[0]["ate"] is None and rows[0]["unit"] == "?"
    assert rows[1]["status"] == "ok" and rows[1]["unit"] == "px" and np.isfinite(rows[1]["ate"])
