"""Upload flood: a slow upload, then many small concurrent ones; does the API still answer?

Reproduces issue 17 item 1. A real server (``uvicorn --factory app.main:create_app``, viewer
off, a fresh data directory) gets:

1. one slow upload: a ``.tar`` of ``--frames`` tiny PCD frames (100,000: some 10 s to read);
2. once it is being read, ``--uploads`` small ``.npz`` uploads at once (45), each on its own
   connection;
3. all along, ``GET /api/health`` and ``GET /api/methods`` every 50 ms, timed.

Prints a table (latency of health and methods while the flood lasts, the uploads' answers
and how long they took) and one JSON line. ``--code-root`` picks the code to serve, so the
same script measures a checkout before and after a change::

    python benchmarks/upload_flood.py --code-root /path/to/old/checkout
    python benchmarks/upload_flood.py
"""

from __future__ import annotations

import argparse
import http.client
import io
import json
import multiprocessing
import os
import socket
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def slow_tar(frames: int) -> bytes:
    from strep_core.io.pcd import format_pcd

    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for i in range(frames):
            data = format_pcd(rng.uniform(0, 1, (3, 2)))
            info = tarfile.TarInfo(f"{i:06d}.pcd")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def small_npz() -> bytes:
    rng = np.random.default_rng(1)
    poses = np.repeat(np.eye(3)[None], 4, axis=0)
    poses[:, :2, 2] = rng.normal(size=(4, 2))
    buf = io.BytesIO()
    np.savez(buf, points=rng.normal(size=(4 * 32, 2)), counts=np.full(4, 32), poses=poses)
    return buf.getvalue()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--code-root", type=Path, default=REPO, help="checkout to serve")
    parser.add_argument("--frames", type=int, default=100_000, help="frames of the slow upload")
    parser.add_argument("--uploads", type=int, default=45, help="small concurrent uploads")
    args = parser.parse_args()

    tar = slow_tar(args.frames)
    npz = small_npz()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="strep-flood-") as data_dir:
        env = {
            **os.environ,
            "PYTHONPATH": str(args.code_root),
            "STREP_DATA_DIR": data_dir,
            "STREP_VIEWER_ENABLED": "false",
        }
        cmd = [sys.executable, "-m", "uvicorn", "--factory", "app.main:create_app", "--port", str(port)]
        server = subprocess.Popen(cmd, cwd=args.code_root, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        load_before = os.getloadavg()
        try:
            result = flood(base, tar, npz, args.uploads)
        finally:
            server.terminate()
            server.wait(30)
    load = {"before": [round(v, 2) for v in load_before], "after": [round(v, 2) for v in os.getloadavg()]}
    result = {
        "code_root": str(args.code_root),
        "frames": args.frames,
        "cpus": os.cpu_count(),
        "loadavg": load,
        **result,
    }
    report(result)


def probe(base: str, route: str, stop: Any, results: Any) -> None:
    """GET ``route`` every 50 ms until ``stop``; puts ``(route, [(ms, perf_counter at start)])``."""
    samples: list[tuple[float, float]] = []
    host, port = base.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=300)
    while not stop.is_set():
        t = time.perf_counter()
        conn.request("GET", route)
        conn.getresponse().read()
        samples.append((1000 * (time.perf_counter() - t), t))
        stop.wait(0.05)
    conn.close()
    results.put((route, samples))


def post_file(base: str, name: str, data: bytes) -> int:
    """POST ``data`` as the ``file`` part of a multipart upload; the answer's status (plain
    http.client: a load generator light on the CPU it shares with the server)."""
    host, port = base.removeprefix("http://").split(":")
    head = f'--B0undary\r\nContent-Disposition: form-data; name="file"; filename="{name}"\r\n\r\n'.encode()
    body = head + data + b"\r\n--B0undary--\r\n"
    conn = http.client.HTTPConnection(host, int(port), timeout=300)
    try:
        conn.request("POST", "/api/sequences", body, {"Content-Type": "multipart/form-data; boundary=B0undary"})
        response = conn.getresponse()
        response.read()
        return response.status
    finally:
        conn.close()


def flood(base: str, tar: bytes, npz: bytes, uploads: int) -> dict[str, object]:
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(f"{base}/api/health", timeout=2).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline:
            raise SystemExit("the server did not start")
        time.sleep(0.1)

    # the probes run in processes of their own: the flood's client threads must not delay them
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    results = ctx.Queue()
    routes = ("/api/health", "/api/methods")
    probers = [ctx.Process(target=probe, args=(base, r, stop, results), daemon=True) for r in routes]
    for proc in probers:
        proc.start()
    time.sleep(2.0)  # the probes are running

    started = time.perf_counter()
    answers: list[tuple[str, int, float]] = []
    lock = threading.Lock()

    def post(name: str, data: bytes) -> None:
        t = time.perf_counter()
        try:
            status = post_file(base, name, data)
        except OSError as exc:
            status = -1
            print(f"{name}: {type(exc).__name__}", file=sys.stderr)
        with lock:
            answers.append((name, status, time.perf_counter() - t))

    slow = threading.Thread(target=post, args=("slow.tar", tar))
    slow.start()
    time.sleep(1.0)  # the slow upload is sent and being read
    small = [threading.Thread(target=post, args=(f"small{i}.npz", npz)) for i in range(uploads)]
    for t in small:
        t.start()
    for t in [slow, *small]:
        t.join()
    seconds = time.perf_counter() - started
    stop.set()
    probes: dict[str, list[float]] = {}
    slowest: list[tuple[float, float, str]] = []  # (ms, at s, route)
    for _ in routes:
        route, samples = results.get(timeout=60)
        during = [(ms, at - started) for ms, at in samples if 0 <= at - started <= seconds]
        probes[route] = [ms for ms, _ in during]
        slowest += [(ms, at, route) for ms, at in during]
    for proc in probers:
        proc.join(30)

    lat = {
        route: {
            "count": len(v),
            "p50_ms": round(percentile(v, 50), 1),
            "p99_ms": round(percentile(v, 99), 1),
            "max_ms": round(max(v, default=float("nan")), 1),
        }
        for route, v in probes.items()
    }
    statuses: dict[str, int] = {}
    for _, status, _ in answers:
        statuses[str(status)] = statuses.get(str(status), 0) + 1
    small_times = [s for name, _, s in answers if name.startswith("small")]
    slow_time = next(s for name, _, s in answers if name == "slow.tar")
    slow_status = next(st for name, st, _ in answers if name == "slow.tar")
    small_started = 1.0
    return {
        "seconds": round(seconds, 1),
        "slowest_probes": [
            {"ms": round(ms, 1), "at_s": round(at, 2), "route": route} for ms, at, route in sorted(slowest)[-5:]
        ],
        "small_uploads_started_at_s": small_started,
        "latency": lat,
        "upload_statuses": statuses,
        "slow_upload": {"status": slow_status, "seconds": round(slow_time, 2)},
        "small_uploads_max_seconds": round(max(small_times, default=0.0), 2),
        "small_uploads_p50_seconds": round(percentile(small_times, 50), 2),
    }


def report(r: dict[str, object]) -> None:
    print(f"code: {r['code_root']}  slow upload: {r['frames']} frames  run: {r['seconds']} s")
    load: dict[str, list[float]] = r["loadavg"]  # type: ignore[assignment]
    print(f"{r['cpus']} CPUs, load average (1, 5, 15 min) before {load['before']}, after {load['after']}")
    print(f"{'route':<14} {'calls':>6} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for route, v in r["latency"].items():  # type: ignore[attr-defined]
        print(f"{route:<14} {v['count']:>6} {v['p50_ms']:>8} {v['p99_ms']:>8} {v['max_ms']:>8}")
    print(f"slow upload: {r['slow_upload']}")
    print(f"upload answers: {r['upload_statuses']}")
    print(f"small uploads: p50 {r['small_uploads_p50_seconds']} s, max {r['small_uploads_max_seconds']} s")
    print(json.dumps(r))


if __name__ == "__main__":
    main()
