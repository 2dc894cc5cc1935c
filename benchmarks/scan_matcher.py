"""Cost and correctness of the global 2D scan matcher on CARMEN keyframes (issue 16).

For each log and window: every consecutive keyframe pair (k-1, k) matched scan to scan from
identity by `strep_core.scanmatch` with the default settings of `ClassicalConfig` (window 1.5,
cell 0.025 and range 8 times the scale; 1 degree; no prior), and the default 2D front end
(`incremental_icp` with the profile the probe picks, laser-keyframes: ICP from the velocity guess
and from the global match against a local map of 5 frames, the matcher's score with the step
prior choosing, the weak-direction guard). A pair is correct within 2 degrees
and 10 cm of the reference relative pose. Prints a table and one JSON line.

    PYTHONPATH=. .venv/bin/python benchmarks/scan_matcher.py [--windows 0:100,300:400] [--whole]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from strep_core import geometry as g
from strep_core import metrics, profiles
from strep_core import registration as reg
from strep_core.config import ClassicalConfig
from strep_core.io.carmen import read_carmen
from strep_core.scanmatch import ScanMatcher

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"


def _ok(truth: np.ndarray, found: np.ndarray) -> np.ndarray:
    err = g.relative(truth, found)
    yaw = np.degrees(np.abs(np.arctan2(err[:, 1, 0], err[:, 0, 0])))
    return (yaw <= 2.0) & (np.linalg.norm(err[:, :2, 2], axis=1) <= 0.1)


def measure(log: str, window: str, front_end: bool) -> dict[str, object]:
    seq = dataclasses.replace(read_carmen(DATA / f"{log}-corrected.log.gz", frames=window), initial_poses=None)
    params = reg.resolve_params(seq, ClassicalConfig()).global_match
    assert params is not None
    truth = g.relative(seq.poses[:-1], seq.poses[1:])
    found, cost, exact = [], [], 0
    for k in range(1, len(seq)):
        t0 = time.perf_counter()
        res = ScanMatcher(seq.frames[k - 1], params).match(seq.frames[k])
        cost.append(time.perf_counter() - t0)
        found.append(res.pose)
        exact += res.exact
    row: dict[str, object] = {
        "log": log,
        "window": window,
        "pairs": len(truth),
        "matcher_ok": int(_ok(truth, np.stack(found)).sum()),
        "matcher_ms_median": 1000 * float(np.median(cost)),
        "matcher_ms_mean": 1000 * float(np.mean(cost)),
        "matcher_ms_p95": 1000 * float(np.percentile(cost, 95)),
        "exact": exact,
        "cell_m": params.resolution,
    }
    if front_end:
        # the front end as a run with the defaults has it: the profile the probe picks
        cfg = ClassicalConfig.model_validate(profiles.overlay(profiles.probe(seq).profile, seq).get("classical", {}))
        rp = reg.resolve_params(seq, cfg)
        out = reg.incremental_icp(seq, np.repeat(np.eye(3)[None], len(seq), 0), rp)
        est = g.relative(out.poses[:-1], out.poses[1:])
        row |= {
            "front_end_ok": int(_ok(truth, est).sum()),
            "front_end_ms_per_pair": 1000 * out.seconds / len(truth),
            "front_end_ate_m": metrics.ate(out.poses, seq.poses),
        }
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", default="intel,aces,belgioioso")
    ap.add_argument("--windows", default="0:100,300:400")
    ap.add_argument("--whole", action="store_true", help="also every pair of each whole log")
    ap.add_argument("--no-front-end", action="store_true", help="the matcher alone")
    args = ap.parse_args()
    windows = args.windows.split(",") + ([":"] if args.whole else [])
    rows = [measure(log, w, not args.no_front_end) for log in args.logs.split(",") for w in windows]
    head = (
        "| log[window] | pairs | matcher ok | ms/pair median (mean, p95) | exact "
        "| front end ok | front end ms/pair | ATE m |"
    )
    print(head)
    print("|---" * (head.count("|") - 1) + "|")
    for r in rows:
        fe = (
            f"{r['front_end_ok']} | {r['front_end_ms_per_pair']:.0f} | {r['front_end_ate_m']:.3f}"
            if "front_end_ok" in r
            else "- | - | -"
        )
        print(
            f"| {r['log']}[{r['window']}] | {r['pairs']} | {r['matcher_ok']} | {r['matcher_ms_median']:.1f} "
            f"({r['matcher_ms_mean']:.1f}, {r['matcher_ms_p95']:.1f}) | {r['exact']} | {fe} |"
        )
    print(json.dumps({"benchmark": "scan_matcher", "rows": rows}))


if __name__ == "__main__":
    main()
