"""Load test of the STREP Studio API on loopback: latency while two jobs optimise, and event delay.

Starts ``python -m app.server`` on a free 127.0.0.1 port with a temporary data directory,
keeps two jobs optimising (``--method``: ``strep`` when it is registered, else ``icp``) on a
bundled sample and follows each with Server-Sent Events, while a few clients send a bounded
number of API requests. Only loopback traffic; the server and its workers are stopped at the end.

Reports:

* API latency: p50 / p99 / max per endpoint and overall, in ms (aim: p99 < 100 ms);
* event delay: from an iteration event's emission in the worker (its ``at`` in the job store)
  to its arrival at an SSE client, in ms (aim: < 250 ms).

Usage::

    python benchmarks/load_api.py [--duration 20] [--requests 800] [--clients 4] [--method icp]
                                  [--sequence sample:sim2d-small] [--viewer-clients 1] [--json results.json]

The machine's load average (before and after the measurement) and the API process's own CPU
use are printed beside the figures: on a shared machine they say what the latency means.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ACTIVE = {"queued", "running"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0}
    arr = np.asarray(values)
    return {
        "n": len(values),
        "p50": float(np.percentile(arr, 50)),
        "p99": float(np.percentile(arr, 99)),
        "max": float(arr.max()),
    }


@dataclass
class Run:
    url: str
    data_dir: Path
    method: str
    sequence: str
    config: dict[str, Any]
    stop: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)
    jobs: list[str] = field(default_factory=list)
    received: list[tuple[str, int, str, float]] = field(default_factory=list)  # job, id, kind, time
    latencies: dict[str, list[float]] = field(default_factory=dict)
    two_running: threading.Event = field(default_factory=threading.Event)
    threads: list[threading.Thread] = field(default_factory=list)


def follow(run: Run, job_id: str) -> None:
    """Read a job's SSE stream to its end, stamping each event's arrival."""
    with httpx.Client(base_url=run.url, timeout=None) as c, c.stream("GET", f"/api/jobs/{job_id}/events") as r:
        event: dict[str, str] = {}
        for line in r.iter_lines():
            if line:
                name, _, value = line.partition(":")
                event[name] = value.strip()
                continue
            if "id" in event:
                with run.lock:
                    run.received.append((job_id, int(event["id"]), event.get("event", ""), time.time()))
            event = {}


def feeder(run: Run) -> None:
    """Keep two jobs active until told to stop; follow each with SSE."""
    with httpx.Client(base_url=run.url, timeout=30) as c:
        while not run.stop.is_set():
            active = [j for j in run.jobs if c.get(f"/api/jobs/{j}").json()["status"] in ACTIVE]
            for _ in range(2 - len(active)):
                body = {"sequence_id": run.sequence, "method": run.method, **run.config}
                r = c.post("/api/jobs", json=body)
                r.raise_for_status()
                job_id = r.json()["id"]
                run.jobs.append(job_id)
                t = threading.Thread(target=follow, args=(run, job_id), daemon=True)
                t.start()
                run.threads.append(t)
            with run.lock:
                iterating = {job for job, _, kind, _ in run.received if kind == "iteration"}
            if len(iterating & set(active)) >= 2:  # two jobs are in their optimisation loops
                run.two_running.set()
            run.stop.wait(0.2)


def client(run: Run, budget: itertools.count, limit: int, deadline: float, think: float, job_ref: list[str]) -> None:
    endpoints = ["/api/health", "/api/jobs?limit=20", "/api/sequences", "JOB"]
    with httpx.Client(base_url=run.url, timeout=30) as c:
        for i in itertools.count():
            if next(budget) >= limit or time.monotonic() > deadline:
                return
            name = endpoints[i % len(endpoints)]
            path = f"/api/jobs/{job_ref[-1]}" if name == "JOB" else name
            t0 = time.perf_counter()
            r = c.get(path)
            dt = (time.perf_counter() - t0) * 1000
            if r.status_code != 200:
                raise RuntimeError(f"{path}: {r.status_code} {r.text[:200]}")
            with run.lock:
                run.latencies.setdefault("GET /api/jobs/{id}" if name == "JOB" else f"GET {name}", []).append(dt)
            time.sleep(think)


def viewer_client(run: Run, port: int, received: list[int]) -> None:
    """A 3D viewer tab: reads everything the viewer's websocket sends until the run stops."""
    import viser
    import websockets.exceptions
    import websockets.sync.client as wsc

    url = f"ws://127.0.0.1:{port}"
    headers = {"Origin": f"http://127.0.0.1:{port}"}
    with wsc.connect(url, subprotocols=[f"viser-v{viser.__version__}"], additional_headers=headers) as ws:  # type: ignore[list-item]
        while not run.stop.is_set():
            try:
                received.append(len(ws.recv(timeout=0.5)))
            except TimeoutError:
                continue
            except websockets.exceptions.ConnectionClosed:
                return


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process so far (Linux /proc), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def event_delays(run: Run) -> list[float]:
    """Arrival minus emission (ms) of every iteration event received."""
    with run.lock:
        received = [r for r in run.received if r[2] == "iteration"]
    with sqlite3.connect(f"file:{run.data_dir / 'strep.db'}?mode=ro", uri=True) as db:
        at = {(job, eid): t for job, eid, t in db.execute("SELECT job_id, id, at FROM events WHERE kind = 'iteration'")}
    return [(t - at[(job, eid)]) * 1000 for job, eid, _, t in received if (job, eid) in at]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds of measurement (at most)")
    parser.add_argument("--requests", type=int, default=800, help="API requests in all (at most)")
    parser.add_argument("--clients", type=int, default=4, help="concurrent API clients")
    parser.add_argument("--think", type=float, default=0.05, help="pause between a client's requests (s)")
    parser.add_argument("--method", help="method of the optimising jobs (default: strep if registered, else icp)")
    parser.add_argument("--sequence", default="sample:sim2d-small", help="sequence id to optimise")
    parser.add_argument("--iterations", type=int, default=100_000, help="optim.iterations for learned methods")
    parser.add_argument("--viewer-clients", type=int, default=0, help="3D viewer tabs reading its websocket")
    parser.add_argument("--json", type=Path, help="write the figures here as JSON")
    args = parser.parse_args(argv)

    from strep_core.methods import available

    methods = available()
    method = args.method or ("strep" if "strep" in methods else "icp")
    learned = methods[method].learned
    config: dict[str, Any] = (
        {"optim": {"iterations": args.iterations, "event_interval": 1}}
        if learned
        else {"classical": {"event_interval_frames": 2}}
    )

    tmp = Path(tempfile.mkdtemp(prefix="strep-load-"))
    port = free_port()
    env = {**os.environ, "STREP_MAX_CONCURRENT_JOBS": "2"}
    env.pop("STREP_API_TOKEN", None)
    log = (tmp / "server.log").open("wb")
    cmd = [sys.executable, "-m", "app.server", "--port", str(port), "--data-dir", str(tmp / "data")]
    server = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=log, env=env)
    run = Run(f"http://127.0.0.1:{port}", tmp / "data", method, args.sequence, config)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{run.url}/api/health", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if server.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the server did not start; see " + str(tmp / "server.log"))
            time.sleep(0.1)

        viewer_bytes: list[int] = []
        if args.viewer_clients:
            viewer_port = httpx.get(f"{run.url}/api/health", timeout=10).json()["viewer_port"]
            if viewer_port is None:
                raise RuntimeError("--viewer-clients: the server has no viewer (STREP_VIEWER_ENABLED=false?)")
            for _ in range(args.viewer_clients):
                viewer = threading.Thread(target=viewer_client, args=(run, viewer_port, viewer_bytes), daemon=True)
                viewer.start()
                run.threads.append(viewer)
        feed = threading.Thread(target=feeder, args=(run,), daemon=True)
        feed.start()
        if not run.two_running.wait(180):
            raise RuntimeError("two jobs never optimised at once")
        load_before = os.getloadavg()
        cpu_before = process_cpu_seconds(server.pid)
        viewer_before = sum(viewer_bytes)
        started = time.monotonic()
        budget = itertools.count()
        clients = [
            threading.Thread(
                target=client, args=(run, budget, args.requests, started + args.duration, args.think, run.jobs)
            )
            for _ in range(args.clients)
        ]
        for t in clients:
            t.start()
        for t in clients:
            t.join()
        measured = time.monotonic() - started
        cpu_after = process_cpu_seconds(server.pid)
        load_after = os.getloadavg()
        viewer_mb = (sum(viewer_bytes) - viewer_before) / 1e6
        run.stop.set()
        feed.join()
        with httpx.Client(base_url=run.url, timeout=30) as c:
            for job_id in run.jobs:
                c.delete(f"/api/jobs/{job_id}")
        for t in run.threads:
            t.join(timeout=30)

        all_lat = [v for values in run.latencies.values() for v in values]
        delays = event_delays(run)
        with httpx.Client(base_url=run.url, timeout=30) as c:
            finished = {j: c.get(f"/api/jobs/{j}").json()["status"] for j in run.jobs}
        result = {
            "machine": f"{platform.node()} {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
            "method": method,
            "sequence": args.sequence,
            "jobs_started": len(run.jobs),
            "job_outcomes": {s: list(finished.values()).count(s) for s in sorted(set(finished.values()))},
            "seconds": round(measured, 1),
            "clients": args.clients,
            "viewer_clients": args.viewer_clients,
            "viewer_mb_received": round(viewer_mb, 2),
            "cpus": os.cpu_count(),
            "loadavg_before": [round(v, 2) for v in load_before],
            "loadavg_after": [round(v, 2) for v in load_after],
            "server_cpu_share": None
            if cpu_before is None or cpu_after is None
            else round((cpu_after - cpu_before) / measured, 3),
            "latency_ms": {
                "all": percentiles(all_lat),
                **{k: percentiles(v) for k, v in sorted(run.latencies.items())},
            },
            "event_delay_ms": percentiles(delays),
        }
    finally:
        run.stop.set()
        if server.poll() is None:
            server.send_signal(signal.SIGINT)
            try:
                server.wait(timeout=30)
            except subprocess.TimeoutExpired:
                server.kill()
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)

    print(
        f"{result['method']} on {result['sequence']}: {result['jobs_started']} jobs, {result['seconds']} s measured, "
        f"{result['clients']} clients, {result['viewer_clients']} viewer tabs ({result['machine']})"
    )
    print(
        f"load average (1, 5, 15 min) before {result['loadavg_before']}, after {result['loadavg_after']}; "
        f"API process CPU {result['server_cpu_share']} cores; viewer sent {result['viewer_mb_received']} MB"
    )
    print(f"{'':28s} {'n':>6s} {'p50 ms':>8s} {'p99 ms':>8s} {'max ms':>8s}")
    rows = [*((f"latency {k}", v) for k, v in result["latency_ms"].items()), ("event delay", result["event_delay_ms"])]
    for name, p in rows:
        if p["n"]:
            print(f"{name:28s} {p['n']:6d} {p['p50']:8.1f} {p['p99']:8.1f} {p['max']:8.1f}")
        else:
            print(f"{name:28s} {0:6d}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
