"""The planar-laser front and back end on the eight CARMEN logs: ATE, time, peak memory, verdicts.

Each run is ``multiway`` with every default (`strep_core.registration.laser_slam`) in its own
process, so its peak resident memory (``VmHWM``) is its own. Prints a table and writes a JSON.

    PYTHONPATH=. python benchmarks/laser_logs.py --out docs/bench/laser-logs.json
    PYTHONPATH=. python benchmarks/laser_logs.py --logs intel aces --windows all
    PYTHONPATH=. python benchmarks/laser_logs.py --frontend icp   # the ICP chain and Open3D graph before
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

LOGS = ("intel", "aces", "belgioioso", "acapulco", "edmonton", "freiburg-079", "freiburg-campus", "infinite-corridor")
DATA = Path("../shared/data/carmen")


def peak_mb() -> int:
    """This process's peak resident memory (Linux's ``VmHWM``), in MB."""
    status = Path("/proc/self/status").read_text().splitlines()
    return round(next(int(line.split()[1]) for line in status if line.startswith("VmHWM")) / 1024)


def one(log: str, window: str, method: str, frontend: str) -> dict[str, object]:
    """Run in this process; returns the row (called in a child by `main`)."""
    from strep_core.config import RunConfig
    from strep_core.io.carmen import read_carmen
    from strep_core.runner import run

    seq = read_carmen(DATA / f"{log}-corrected.log.gz", frames=None if window == "all" else window)
    t0 = time.perf_counter()
    cfg = {"method": method, "classical": {"posegraph": {"frontend": frontend}}}
    res = run(seq, RunConfig.model_validate(cfg))
    wall = time.perf_counter() - t0
    m = res.metrics
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "log": log,
        "window": window,
        "method": method,
        "frontend": frontend,
        "scans": len(seq),
        "ate": m["ate"],
        "initial_ate": m.get("initial_ate"),
        "wall_seconds": round(wall, 1),
        "cpu_seconds": round(usage.ru_utime + usage.ru_stime, 1),  # the whole process: steadier under load
        "ms_per_scan": round(1000 * wall / len(seq), 1),
        "peak_mb": peak_mb(),
        "failed": m.get("matches_failed"),
        "ambiguous": m.get("matches_ambiguous"),
        "loops_kept": m.get("loops_kept"),
        "loops_rejected": m.get("loops_rejected"),
        "loop_passes": res.artifacts.get("loop_passes"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=list(LOGS))
    ap.add_argument("--windows", nargs="+", default=["0:100", "300:400", "all"])
    ap.add_argument("--method", default="multiway")
    ap.add_argument("--frontend", default="auto", choices=["auto", "submaps", "icp"], help="icp: the old chain")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--one", nargs=4, metavar=("LOG", "WINDOW", "METHOD", "FRONTEND"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(*args.one)))
        return
    rows = []
    print(
        f"{'log':<18} {'window':<8} {'scans':>5} {'ATE m':>7} {'s':>6} {'cpu s':>6} {'ms/scan':>7} {'MB':>5}"
        f" {'fail':>4} {'amb':>4} {'loops':>5}"
    )
    for log in args.logs:
        for w in args.windows:
            cmd = [sys.executable, __file__, "--one", log, w, args.method, args.frontend]
            out = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if out.returncode:
                rows.append({"log": log, "window": w, "error": out.stderr.strip().splitlines()[-1:]})
                print(f"{log:<18} {w:<8} failed: {rows[-1]['error']}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(r)
            print(
                f"{log:<18} {w:<8} {r['scans']:>5} {r['ate']:>7.3f} {r['wall_seconds']:>6.1f} {r['cpu_seconds']:>6.1f}"
                f" {r['ms_per_scan']:>7.1f} {r['peak_mb']:>5} {r['failed']!s:>4} {r['ambiguous']!s:>4}"
                f" {r['loops_kept']!s:>5}",
                flush=True,
            )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
