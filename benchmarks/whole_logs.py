"""Whole CARMEN logs with the defaults (`strep run LOG --method multiway`): ATE, wall time, and a
plot of time against scans (issue 16, docs/design/scan-matching.md).

    PYTHONPATH=. python benchmarks/whole_logs.py --logs intel,aces,belgioioso --out /tmp/whole
    PYTHONPATH=. python benchmarks/whole_logs.py --plot /tmp/whole/whole_logs.json --png docs/design/whole-logs.png

The run's progress history gives the elapsed time after every 10th scan: the first K steps are
the front end (incremental ICP with the global scan matcher), the next K the loop closures.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"


def run_logs(logs: list[str], method: str, out: Path) -> dict:
    from strep_core.config import RunConfig
    from strep_core.runner import run_input

    report: dict = {}
    for log in logs:
        started = time.perf_counter()
        res = run_input(DATA / f"{log}-corrected.log.gz", RunConfig(method=method), out_dir=out / log)
        report[log] = {
            "method": method,
            "frames": res.metrics["frames"],
            "ate": res.metrics["ate"],
            "wall_seconds": time.perf_counter() - started,
            "timings": res.timings,
            "profile": res.config.profile,
            "loop_edges": res.artifacts.get("loop_edges"),
            "loop_candidates": res.artifacts.get("loop_candidates"),
            "history": res.history,
        }
        print(log, {k: v for k, v in report[log].items() if k != "history"}, flush=True)
        (out / "whole_logs.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    return report


def plot(report: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for log, r in report.items():
        k = r["frames"]
        hist = r["history"]
        front = [(h["iteration"], h["elapsed"]) for h in hist if h["iteration"] <= k]
        loops = [(h["iteration"] - k, h["elapsed"]) for h in hist if h["iteration"] > k]
        (line,) = ax.plot(*zip(*front, strict=True), label=f"{log}: front end")
        if loops:
            ax.plot(*zip(*loops, strict=True), "--", color=line.get_color(), label=f"{log}: + loop closures")
        ax.annotate(f"{r['ate']:.2f} m", (k, r["wall_seconds"]), fontsize=8)
    ax.set_xlabel("scans")
    ax.set_ylabel("seconds since the start")
    ax.set_title("Whole CARMEN logs, multiway with the defaults (2 shared CPU cores)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", default="intel,aces,belgioioso")
    parser.add_argument("--method", default="multiway")
    parser.add_argument("--out", type=Path, default=Path("/tmp/whole_logs"))
    parser.add_argument("--plot", type=Path, help="plot this whole_logs.json instead of running")
    parser.add_argument("--png", type=Path, default=Path("docs/design/whole-logs.png"))
    args = parser.parse_args()
    if args.plot is not None:
        report = json.loads(args.plot.read_text())
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        report = run_logs(args.logs.split(","), args.method, args.out)
    plot(report, args.png)
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
