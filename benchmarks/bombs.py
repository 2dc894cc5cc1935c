"""Decompression bombs against the upload reader: time and peak memory (issue 17 item 2).

Builds three files of about 1 MB that inflate to 1 GiB each:

* ``bomb.npz``: ``points.npy`` of 67 million 2D points (zeros), ``counts`` for 8 frames;
* ``bomb.tar``: a *gzip* tar named ``.tar`` holding two PCD frames of 44.7 million points each;
* ``bomb.log.gz``: a CARMEN log of 4 FLASER lines and 1 GiB of comment lines.

Each is read in a fresh process exactly as the service's reader reads an upload
(`app.services.worker.load_source` with the service's limits), which prints the outcome, the
wall time and the process's peak RSS. ``--code-root`` picks the code to measure, so the same
script measures a checkout before and after a change::

    python benchmarks/bombs.py --code-root /path/to/old/checkout
    python benchmarks/bombs.py                        # this checkout
    python benchmarks/bombs.py --max-inflated-mib 256 # a smaller budget

``--body-mib N`` adds issue 17 item 3: a real server (``uvicorn --factory
app.main:create_app`` with a token, viewer off) is sent an N MiB JSON body (300 in the issue)
without the token; printed: the answer's status, the seconds until it came and the server's
RSS before and after (``--body-mib 0`` skips it).

Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path

import numpy as np

GiB = 1024**3
ZEROS = bytes(1 << 20)
REPO = Path(__file__).resolve().parents[1]


def write_zeros(out: io.BufferedIOBase | gzip.GzipFile | zipfile.ZipExtFile, size: int) -> None:
    while size > 0:
        n = min(size, len(ZEROS))
        out.write(ZEROS[:n])
        size -= n


def make_npz(path: Path) -> None:
    points = GiB // 16  # 2D float64
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("points.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (points, 2)})
            write_zeros(f, points * 16)  # type: ignore[arg-type]
        buf = io.BytesIO()
        np.save(buf, np.full(8, points // 8, dtype=np.int64))
        zf.writestr("counts.npy", buf.getvalue())


def pcd_header(points: int) -> bytes:
    return (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA binary\n"
    ).encode()


def make_tar(path: Path) -> None:
    points = GiB // 2 // 12
    with gzip.open(path, "wb") as gz, tarfile.open(fileobj=gz, mode="w|") as tar:  # type: ignore[call-overload]
        for i in range(2):
            head = pcd_header(points)
            info = tarfile.TarInfo(f"{i:03d}.pcd")
            info.size = len(head) + points * 12
            tar.addfile(info, io.BufferedReader(_Frame(head, points * 12)))


class _Frame(io.RawIOBase):
    def __init__(self, head: bytes, size: int) -> None:
        self.data = head
        self.left = size

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: memoryview) -> int:  # type: ignore[override]
        if self.data:
            n = min(len(buffer), len(self.data))
            buffer[:n] = self.data[:n]
            self.data = self.data[n:]
            return n
        n = min(len(buffer), self.left)
        buffer[:n] = bytes(n)
        self.left -= n
        return n


def make_log(path: Path) -> None:
    beams = 180
    ranges = " ".join(f"{2 + 0.01 * b:.2f}" for b in range(beams))
    comment = b"#" + b"x" * 1022 + b"\n"
    with gzip.open(path, "wb") as gz:
        for i in range(4):
            gz.write(f"FLASER {beams} {ranges} {0.1 * i} 0 0 {0.1 * i} 0 0 {i} h {i}\n".encode())
        block = comment * 1024
        for _ in range(GiB // len(block)):
            gz.write(block)


CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, sys.argv[1])
from app.services.worker import load_source
path, max_bytes, max_points = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
t = time.perf_counter()
try:
    try:
        seq = load_source(path, None, max_bytes, sys.argv[5], max_points)
    except TypeError:  # code from before the point limit
        seq = load_source(path, None, max_bytes, sys.argv[5])
    outcome = f"accepted: {len(seq)} frames, {seq.num_points} points"
except Exception as exc:
    outcome = f"{type(exc).__name__}: {str(exc)[-110:]}"
seconds = time.perf_counter() - t
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"outcome": outcome, "seconds": round(seconds, 2), "peak_rss_mib": round(rss)}))
"""


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    return float("nan")


def body_bomb(code_root: Path, mib: int) -> dict[str, object]:
    """POST ``mib`` MiB of JSON without the token to a server that has one (item 3)."""
    import os
    import socket
    import time

    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory(prefix="strep-body-") as data_dir:
        env = {**os.environ, "PYTHONPATH": str(code_root), "STREP_DATA_DIR": data_dir}
        env.update(STREP_VIEWER_ENABLED="false", STREP_API_TOKEN="s3cret")
        cmd = [sys.executable, "-m", "uvicorn", "--factory", "app.main:create_app", "--port", str(port)]
        server = subprocess.Popen(cmd, cwd=code_root, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    httpx.get(f"{base}/api/health", timeout=2)
                    break
                except httpx.TransportError:
                    if time.monotonic() > deadline:
                        raise RuntimeError("the server did not start") from None
                    time.sleep(0.2)
            before = rss_mib(server.pid)
            chunk = b" " * (1 << 20)

            def body():  # type: ignore[no-untyped-def]
                yield b'{"sequence_id": "sample:sim2d-small", "method": "identity", "name": "'
                for _ in range(mib):
                    yield chunk
                yield b'"}'

            t = time.perf_counter()
            try:
                r = httpx.post(
                    f"{base}/api/jobs", content=body(), headers={"Content-Type": "application/json"}, timeout=600
                )
                status: object = r.status_code
            except httpx.TransportError as exc:  # the server may close the connection once it has answered
                status = f"connection closed ({type(exc).__name__})"
            seconds = round(time.perf_counter() - t, 2)
            return {
                "body_mib": mib,
                "status": status,
                "seconds": seconds,
                "rss_mib_before": before,
                "rss_mib_after": rss_mib(server.pid),
            }
        finally:
            server.terminate()
            server.wait(30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--code-root", type=Path, default=REPO, help="checkout whose reader is measured")
    parser.add_argument("--max-inflated-mib", type=int, default=2048, help="the service's default: 2048")
    parser.add_argument("--max-points", type=int, default=20_000_000, help="the service's default: 20 million")
    parser.add_argument("--body-mib", type=int, default=300, help="JSON body without the token (0: skip)")
    args = parser.parse_args()
    body = body_bomb(args.code_root, args.body_mib) if args.body_mib else None
    rows = []
    with tempfile.TemporaryDirectory(prefix="strep-bombs-") as tmp:
        folder = Path(tmp)
        extract = folder / "extract"
        extract.mkdir()
        for name, make in (("bomb.npz", make_npz), ("bomb.tar", make_tar), ("bomb.log.gz", make_log)):
            path = folder / name
            make(path)
            cmd = [sys.executable, "-c", CHILD, str(args.code_root), str(path)]
            cmd += [str(args.max_inflated_mib * 1024**2), str(args.max_points), str(extract)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=False)
            try:
                row = json.loads(out.stdout.strip().splitlines()[-1])
            except (IndexError, json.JSONDecodeError):
                row = {"outcome": f"reader died (code {out.returncode}): {out.stderr[-200:]}"}
            rows.append({"file": name, "size_bytes": path.stat().st_size, **row})
    print(f"code: {args.code_root}  limits: {args.max_inflated_mib} MiB inflated, {args.max_points} points")
    print(f"{'file':<12} {'size':>9} {'seconds':>8} {'peak RSS':>9}  outcome")
    for r in rows:
        print(
            f"{r['file']:<12} {r['size_bytes']:>9} {r.get('seconds', '-'):>8} "
            f"{str(r.get('peak_rss_mib', '-')) + ' MiB':>9}  {r['outcome']}"
        )
    if body is not None:
        print(
            f"{body['body_mib']} MiB JSON body without the token: {body['status']} after {body['seconds']} s, "
            f"server RSS {body['rss_mib_before']} -> {body['rss_mib_after']} MiB"
        )
    result = {"code_root": str(args.code_root), "max_inflated_mib": args.max_inflated_mib, "rows": rows, "body": body}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
