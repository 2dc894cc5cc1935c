"""Whole planar-laser logs from several start headings: the spread a rule is judged by.

A whole log's ATE is one draw: a start heading, or the last bits of the BLAS kernels on
another CPU, moves the corridor by tenths of a metre (docs/design/laser-slam.md, rounds 10 and
17). This runs `laser_slam` with every default on each (log, heading) in its own process, two
at a time, prints a table and writes a JSON; each run's pose graph (``matches.json``, as
`LaserSlamResult.report`) and poses are kept beside it, so `benchmarks/graph_trials.py` can
re-solve them under another back end in seconds.

    PYTHONPATH=. python benchmarks/laser_headings.py --out /tmp/headings           # the 14 runs
    PYTHONPATH=. python benchmarks/laser_headings.py --logs intel --headings 0 90 --out /tmp/h
    PYTHONPATH=. python benchmarks/laser_headings.py --blas-core Sandybridge --out /tmp/h2  # another draw

``--blas-core`` sets ``OPENBLAS_CORETYPE`` in the children: OpenBLAS picks its kernels by CPU
(Haswell on an AVX2 machine, SkylakeX with AVX-512), and their rounding is what moves a run from
one machine to another (numpy's own SIMD dispatch, ``NPY_DISABLE_CPU_FEATURES``, moves nothing
here). The same code on the same data, rounded as another CPU rounds (round 17).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from laser_logs import DATA, peak_mb  # a sibling script: run from benchmarks/, as the usage says

# every log from identity (the longest first, so two at a time finish together), and the two
# that move most at three more headings (rounds 13-17)
LONGEST_FIRST = ("freiburg-079", "infinite-corridor", "freiburg-campus", "intel", "aces", "belgioioso", "acapulco")
DEFAULT_RUNS = [(log, 0.0) for log in (*LONGEST_FIRST, "edmonton")] + [
    (log, deg) for deg in (60.0, 135.0, 225.0) for log in ("infinite-corridor", "freiburg-campus")
]


def one(log: str, heading: float, out: Path) -> dict[str, object]:
    """Run in this process; saves ``out/matches.json`` and ``out/poses.npz``, returns the row."""
    import dataclasses

    import numpy as np

    from strep_core import geometry as g
    from strep_core.io.carmen import read_carmen
    from strep_core.metrics import ate
    from strep_core.registration.laser_slam import laser_slam

    seq = read_carmen(DATA / f"{log}-corrected.log.gz")
    gt = seq.poses
    seq = dataclasses.replace(seq, initial_poses=None)
    t0 = time.perf_counter()
    res = laser_slam(seq, g.se2_from_xytheta(np.array([0.0, 0.0, np.radians(heading)])))
    wall = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    (out / "matches.json").write_text(json.dumps(res.report()))
    np.savez(out / "poses.npz", poses=res.poses, local=res.local_poses, gt=gt)
    return {
        "log": log,
        "heading": heading,
        "scans": len(seq),
        "ate": round(float(ate(res.poses, gt)), 4),
        "local_ate": round(float(ate(res.local_poses, gt)), 3),
        "wall_seconds": round(wall, 1),
        "peak_mb": peak_mb(),
        **res.verdicts(),
        "loops": len(res.loops),
        "loops_kept": res.loops_kept,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", help="these logs at --headings (default: the 14 runs of rounds 13-17)")
    ap.add_argument("--headings", nargs="+", type=float, default=[0.0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--blas-core", help="OPENBLAS_CORETYPE for the runs, e.g. Sandybridge: another CPU's rounding")
    ap.add_argument("--out", type=Path, help="a folder: runs.json and one folder per run (required)")
    ap.add_argument("--one", nargs=3, metavar=("LOG", "HEADING", "DIR"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one[0], float(args.one[1]), Path(args.one[2]))))
        return
    if args.out is None:
        ap.error("--out is required")
    runs = [(log, h) for log in args.logs for h in args.headings] if args.logs else DEFAULT_RUNS
    env = dict(os.environ)
    if args.blas_core:
        env["OPENBLAS_CORETYPE"] = args.blas_core

    def child(run: tuple[str, float]) -> dict[str, object]:
        log, h = run
        cmd = [sys.executable, __file__, "--one", log, str(h), str(args.out / f"{log}-{h:g}")]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
        if done.returncode:
            return {"log": log, "heading": h, "error": done.stderr.strip().splitlines()[-1:]}
        return json.loads(done.stdout.strip().splitlines()[-1])

    head = f"{'log':<18} {'deg':>4} {'scans':>5} {'ATE m':>7} {'local':>7} {'s':>6} {'MB':>5} {'fail':>4} {'amb':>4}"
    print(f"{head} {'loops':>9}")
    rows = []
    with ThreadPoolExecutor(args.jobs) as pool:
        for r in pool.map(child, runs):
            rows.append(r)
            if "error" in r:
                print(f"{r['log']:<18} {r['heading']:>4g} failed: {r['error']}", flush=True)
                continue
            print(
                f"{r['log']:<18} {r['heading']:>4g} {r['scans']:>5} {r['ate']:>7.3f} {r['local_ate']:>7.2f}"
                f" {r['wall_seconds']:>6.1f} {r['peak_mb']:>5} {r['failed']:>4} {r['ambiguous']:>4}"
                f" {r['loops_kept']:>4}/{r['loops']:<4}",
                flush=True,
            )
    ok = [r for r in rows if "error" not in r]
    print(f"{sum(float(r['ate']) < 0.5 for r in ok)} of {len(rows)} runs below 0.5 m")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "runs.json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
