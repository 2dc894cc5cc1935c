"""The service as deployed: ``python -m app.server`` (uvicorn) on a free loopback port.

Live Server-Sent Events over a real socket, files over HTTP, cancel, a killed worker, a
killed server restarted on the same data directory, and a graceful stop. Every server this
module starts is stopped by it.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

from strep_core.io.npz import write_npz

ROOT = Path(__file__).resolve().parents[1]
FINAL = {"succeeded", "failed", "cancelled", "interrupted"}
LONG = 100_000  # demo iterations: such jobs never finish by themselves


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Server:
    proc: subprocess.Popen[bytes]
    url: str
    data_dir: Path
    log: Path

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=30)

    def output(self) -> str:
        return self.log.read_text(errors="replace")[-5000:]

    def stop(self, sig: int = signal.SIGINT) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout=10)


def start_server(data_dir: Path, log: Path, *extra: str, wait: bool = True) -> Server:
    port = free_port()
    env = {
        **os.environ,
        "STREP_PLUGINS": "strep_demo_methods",
        "STREP_MAX_CONCURRENT_JOBS": "2",
        "STREP_CANCEL_GRACE_SECONDS": "2",
        "STREP_WORKER_THREADS": "1",
    }
    env.pop("STREP_API_TOKEN", None)
    args = ["--host", "127.0.0.1", "--port", str(port), "--data-dir", str(data_dir), *extra]
    with log.open("ab") as out:
        proc = subprocess.Popen([sys.executable, "-m", "app.server", *args], cwd=ROOT, stdout=out, stderr=out, env=env)
    server = Server(proc, f"http://127.0.0.1:{port}", data_dir, log)
    if not wait:
        return server
    deadline = time.monotonic() + 90
    while True:
        if proc.poll() is not None:
            raise AssertionError(f"the server exited with {proc.returncode}:\n{server.output()}")
        try:
            if httpx.get(f"{server.url}/api/health", timeout=2).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline:
            server.stop(signal.SIGKILL)
            raise AssertionError(f"the server did not answer:\n{server.output()}")
        time.sleep(0.1)


def wait_job(c: httpx.Client, job_id: str, statuses: set[str], *, timeout: float = 120) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        job = c.get(f"/api/jobs/{job_id}").json()
        if job["status"] in statuses:
            return job
        if time.monotonic() > deadline:
            raise AssertionError(f"job {job_id} still {job['status']} after {timeout} s")
        time.sleep(0.05)


def stored_job(data_dir: Path, job_id: str) -> dict[str, Any]:
    """A job's row read straight from the SQLite store (what the pid of its worker is)."""
    with sqlite3.connect(f"file:{data_dir / 'strep.db'}?mode=ro", uri=True) as db:
        db.row_factory = sqlite3.Row
        row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
    return dict(row)


def worker_pid(data_dir: Path, job_id: str, *, min_events: int = 5) -> int:
    """Pid of a job's worker once it has emitted an iteration event (queued, running, stage, start, iteration)."""
    deadline = time.monotonic() + 60
    while True:
        row = stored_job(data_dir, job_id)
        if row["pid"] and row["last_event_id"] >= min_events:
            return int(row["pid"])
        assert time.monotonic() < deadline, f"no worker for {job_id}: {row}"
        time.sleep(0.05)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


class SSE:
    """Reads ``text/event-stream`` incrementally: `next` returns one event at a time."""

    def __init__(self, response: httpx.Response) -> None:
        self.lines = response.iter_lines()

    def next(self) -> dict[str, Any] | None:
        event: dict[str, Any] = {}
        for line in self.lines:
            if not line:
                if event:
                    return event
                continue
            if line.startswith(":"):
                continue
            name, _, value = line.partition(":")
            value = value.removeprefix(" ")
            event[name] = json.loads(value) if name == "data" else int(value) if name == "id" else value
        return event or None

    def rest(self) -> list[dict[str, Any]]:
        out = []
        while (event := self.next()) is not None:
            out.append(event)
        return out


def create_job(c: httpx.Client, sequence_id: str, method: str, **config: Any) -> dict[str, Any]:
    r = c.post("/api/jobs", json={"sequence_id": sequence_id, "method": method, **config})
    assert r.status_code == 201, r.text
    return r.json()


# ---- fixtures --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("served")


@pytest.fixture(scope="module")
def npz(workdir: Path) -> Path:
    from strep_core.sim.lidar2d import simulate_2d

    path = workdir / "sim8.npz"
    write_npz(simulate_2d(4, frames=8), path)
    return path


@pytest.fixture(scope="module")
def server(workdir: Path) -> Iterator[Server]:
    srv = start_server(workdir / "data", workdir / "server.log")
    yield srv
    srv.stop(signal.SIGKILL)


@pytest.fixture(scope="module")
def state() -> dict[str, Any]:
    """What earlier tests made, for the restart test to find again."""
    return {}


# ---- tests -------------------------------------------------------------------------------------


def test_upload_run_stream_and_download(server: Server, npz: Path, state: dict[str, Any]) -> None:
    with server.client() as c, npz.open("rb") as f:
        r = c.post("/api/sequences", files={"file": ("sim8.npz", f)}, data={"name": "served"})
        assert r.status_code == 201, r.text
        seq = r.json()
        job = create_job(c, seq["id"], "icp")
        with c.stream("GET", f"/api/jobs/{job['id']}/events") as resp:
            assert resp.status_code == 200
            assert resp.headers["content-type"].startswith("text/event-stream")
            events = SSE(resp).rest()
        assert [e["id"] for e in events] == list(range(1, len(events) + 1))
        assert events[-1]["event"] == "status" and events[-1]["data"]["status"] == "succeeded"
        assert {"start", "iteration", "result"} <= {e["event"] for e in events}
        done = c.get(f"/api/jobs/{job['id']}").json()
        assert done["metrics"]["ate"] < 0.5 * done["metrics"]["initial_ate"]
        files = {name: c.get(f"/api/jobs/{job['id']}/files/{name}") for name in done["files"]}
        assert all(r.status_code == 200 for r in files.values())
        assert json.loads(files["metrics.json"].content)["ate"] == pytest.approx(done["metrics"]["ate"])
        assert "attachment" in files["map.ply"].headers["content-disposition"]
    state.update(sequence=seq, job=done, files={k: v.content for k, v in files.items()})


def test_strep_job_streams_to_the_end(server: Server) -> None:
    from strep_core.methods import available

    if "strep" not in available():
        pytest.skip("the strep method is not registered yet")
    with server.client() as c:
        job = create_job(
            c,
            "sample:sim2d-small",
            "strep",
            frames="0:12",
            init="identity",
            optim={"iterations": 6, "event_interval": 2},
        )
        with c.stream("GET", f"/api/jobs/{job['id']}/events") as resp:
            events = SSE(resp).rest()
        its = [e["data"] for e in events if e["event"] == "iteration"]
        assert [e["iteration"] for e in its] == [0, 2, 4, 6]  # 0: the starting poses
        assert its[0]["ate"] is not None and all(e["losses"] for e in its[1:])
        assert events[-1]["data"]["status"] == "succeeded"
        done = c.get(f"/api/jobs/{job['id']}").json()
        assert "model.pt" in done["files"]
        assert len(c.get(f"/api/jobs/{job['id']}/files/model.pt").content) > 1000


def test_live_events_then_cancel(server: Server, state: dict[str, Any]) -> None:
    with server.client() as c:
        job = create_job(c, state["sequence"]["id"], "demo-sleep", optim={"iterations": LONG, "event_interval": 5})
        with c.stream("GET", f"/api/jobs/{job['id']}/events") as resp:
            sse = SSE(resp)
            seen = []
            while len([e for e in seen if e["event"] == "iteration"]) < 3:
                event = sse.next()
                assert event is not None, "the stream ended early"
                seen.append(event)
            # the job cannot have finished by itself: these events arrived live
            assert c.get(f"/api/jobs/{job['id']}").json()["status"] == "running"
            assert c.delete(f"/api/jobs/{job['id']}").status_code == 202
            seen += sse.rest()  # the stream ends by itself after the final status
        iterations = [e["data"]["iteration"] for e in seen if e["event"] == "iteration"]
        assert iterations[:3] == [5, 10, 15]
        assert seen[-1]["data"]["status"] == "cancelled"
        assert [e["id"] for e in seen] == list(range(1, len(seen) + 1))


def test_reconnect_with_last_event_id(server: Server, state: dict[str, Any]) -> None:
    with server.client() as c:
        job = create_job(c, state["sequence"]["id"], "demo-sleep", optim={"iterations": LONG, "event_interval": 5})
        with c.stream("GET", f"/api/jobs/{job['id']}/events") as resp:
            sse = SSE(resp)
            first = [sse.next() for _ in range(5)]
        assert [e["id"] for e in first if e] == [1, 2, 3, 4, 5]
        with c.stream("GET", f"/api/jobs/{job['id']}/events", headers={"Last-Event-ID": "5"}) as resp:
            sse = SSE(resp)
            again = [sse.next() for _ in range(2)]
        assert [e["id"] for e in again if e] == [6, 7]
        assert again[0] is not None and again[0]["event"] == "iteration"
        c.delete(f"/api/jobs/{job['id']}")
        assert wait_job(c, job["id"], FINAL)["status"] == "cancelled"


def test_killed_worker_fails_its_job_only(server: Server, state: dict[str, Any]) -> None:
    with server.client() as c:
        victim = create_job(c, state["sequence"]["id"], "demo-sleep", optim={"iterations": LONG})
        other = create_job(c, state["sequence"]["id"], "demo-sleep", optim={"iterations": LONG})
        os.kill(worker_pid(server.data_dir, victim["id"]), signal.SIGKILL)
        failed = wait_job(c, victim["id"], FINAL)
        assert failed["status"] == "failed"
        assert "killed by signal SIGKILL" in failed["error"]
        assert c.get(f"/api/jobs/{other['id']}").json()["status"] == "running"
        assert c.get("/api/health").status_code == 200
        c.delete(f"/api/jobs/{other['id']}")
        assert wait_job(c, other["id"], FINAL)["status"] == "cancelled"


def test_killed_server_restarts_with_everything(server: Server, workdir: Path, state: dict[str, Any]) -> None:
    with server.client() as c:
        long_jobs = [create_job(c, state["sequence"]["id"], "demo-sleep", optim={"iterations": LONG}) for _ in range(3)]
        pids = [worker_pid(server.data_dir, j["id"]) for j in long_jobs[:2]]
        assert c.get(f"/api/jobs/{long_jobs[2]['id']}").json()["status"] == "queued"
    server.stop(signal.SIGKILL)  # the server dies without any chance to clean up
    deadline = time.monotonic() + 30
    while any(alive(pid) for pid in pids):  # its workers notice and exit
        assert time.monotonic() < deadline, "workers outlived their server"
        time.sleep(0.1)

    restarted = start_server(server.data_dir, workdir / "server2.log")
    try:
        with restarted.client() as c:
            # finished work is all there, files byte for byte
            job = c.get(f"/api/jobs/{state['job']['id']}").json()
            assert (job["status"], job["metrics"]) == ("succeeded", state["job"]["metrics"])
            for name, content in state["files"].items():
                assert c.get(f"/api/jobs/{job['id']}/files/{name}").content == content
            assert c.get(f"/api/sequences/{state['sequence']['id']}").json() == state["sequence"]
            replay = SSE(c.get(f"/api/jobs/{job['id']}/events")).rest()
            assert replay[-1]["data"]["status"] == "succeeded"
            # the running jobs were interrupted; the queued one kept its place and starts now
            for j in long_jobs[:2]:
                interrupted = c.get(f"/api/jobs/{j['id']}").json()
                assert interrupted["status"] == "interrupted"
                assert interrupted["error"] == "the service stopped while this job was running"
                events = SSE(c.get(f"/api/jobs/{j['id']}/events")).rest()
                assert events[-1]["data"]["status"] == "interrupted"
                assert c.get(f"/api/jobs/{j['id']}/files/map.ply").status_code == 404
                assert not (restarted.data_dir / "results" / ".tmp" / j["id"]).exists()
            requeued = wait_job(c, long_jobs[2]["id"], {"running"} | FINAL)
            assert requeued["status"] == "running"
            state["running_at_stop"] = requeued["id"]
            worker_pid(restarted.data_dir, requeued["id"])
        # a graceful stop interrupts what runs and exits 0
        assert restarted.stop(signal.SIGINT) == 0
        row = stored_job(restarted.data_dir, state["running_at_stop"])
        assert (row["status"], row["error"]) == ("interrupted", "the service shut down while this job was running")
    finally:
        restarted.stop(signal.SIGKILL)


def test_refuses_a_public_address_without_token(workdir: Path) -> None:
    srv = start_server(workdir / "public", workdir / "public.log", "--host", "0.0.0.0", wait=False)
    try:
        assert srv.proc.wait(timeout=60) == 2
    finally:
        srv.stop(signal.SIGKILL)
    assert "refusing to listen on 0.0.0.0" in srv.output()
    assert not (workdir / "public" / "strep.db").exists()
