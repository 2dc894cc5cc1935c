"""Held-out proxies for the planar-laser local SLAM: 100-scan windows across each CARMEN log,
as recorded and keyframed at twice and three times the spacing (every second, third scan).

Logs kept outside the project differ in their paths and their keyframe spacing. A default is
kept only if it holds on windows it was not chosen on: this runs the local chain alone
(`strep_core.registration.submaps.local_slam`, every default, from the window's reference start
pose) on windows every 300 scans (or every window's span, if longer) and counts those below
0.3 m and 1 m of ATE. Prints a table per stride and writes a JSON of every window.

    PYTHONPATH=. python benchmarks/laser_proxies.py --out docs/bench/laser-proxies.json
    PYTHONPATH=. python benchmarks/laser_proxies.py --logs intel aces --strides 1 2
"""

from __future__ import annotations

import argparse
import json
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

LOGS = ("intel", "aces", "belgioioso", "acapulco", "edmonton", "freiburg-079", "freiburg-campus", "infinite-corridor")
DATA = Path("../shared/data/carmen")
SCANS = 100  # scans per window, after the stride


def windows(log: str, stride: int) -> list[dict[str, object]]:
    """Every window of one log at one stride (run in a worker process)."""
    from strep_core.io.carmen import read_carmen
    from strep_core.metrics import ate
    from strep_core.registration.submaps import derive_params, local_slam

    seq = read_carmen(DATA / f"{log}-corrected.log.gz")
    span = SCANS * stride
    rows = []
    for first in range(0, len(seq) - span + 1, max(span, 300)):
        sub = seq.select(slice(first, first + span, stride))
        poses, matches, _ = local_slam(sub.frames, derive_params(sub), start=sub.poses[0])
        verdicts = [m.verdict for m in matches]
        rows.append(
            {
                "log": log,
                "stride": stride,
                "first": first,
                "ate": round(float(ate(poses, sub.poses)), 4),
                "failed": verdicts.count("failed"),
                "ambiguous": verdicts.count("ambiguous"),
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", default=list(LOGS))
    ap.add_argument("--strides", nargs="+", type=int, default=[1, 2, 3])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    jobs = [(log, s) for s in args.strides for log in args.logs]
    with ProcessPoolExecutor(args.workers) as pool:
        done = list(pool.map(windows, *zip(*jobs, strict=True)))
    rows = [r for part in done for r in part]
    print(f"{'stride':>6} {'windows':>7} {'< 0.3 m':>7} {'< 1 m':>5} {'median m':>8}  worst (log first: m)")
    for s in args.strides:
        mine = [r for r in rows if r["stride"] == s]
        a = np.array([r["ate"] for r in mine])
        worst = sorted(mine, key=lambda r: -float(r["ate"]))[:3]
        print(
            f"{s:>6} {len(a):>7} {(a < 0.3).sum():>7} {(a < 1.0).sum():>5} {np.median(a):>8.3f}  "
            + ", ".join(f"{r['log']} {r['first']}: {r['ate']:.2f}" for r in worst)
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        report = {
            "machine": f"2-core shared CPU, {args.workers} logs at a time",
            "command": "PYTHONPATH=. python benchmarks/laser_proxies.py",
            "rows": rows,
        }
        args.out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
