"""Peak memory and wall time of `strep run` (defaults) on windows of a CARMEN log: the pose-graph
front end and the learned refinement measured apart, in one process (docs/design/whole-logs.md).

    PYTHONPATH=. python benchmarks/refine_memory.py --log intel --frames 400 --label after --out /tmp/mem.jsonl
    PYTHONPATH=. python benchmarks/refine_memory.py --frames 400 --set optim.batch_frames=null --label before ...
    PYTHONPATH=. python benchmarks/refine_memory.py --plot /tmp/mem.jsonl --png docs/design/whole-logs-memory.png

Peak resident memory is Linux's ``VmHWM``: read when the front end hands over (the `StartEvent`),
then reset (``/proc/self/clear_refs``, 5) so the second reading is the refinement's own peak
(it includes what the process already held then: the sequence, the front end's leftovers).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"


def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


class _MemorySink:
    """At the start event: the front end's peak and the resident set then; resets the peak."""

    def __init__(self) -> None:
        self.front_peak_kb = 0
        self.rss_at_start_kb = 0
        self.t_start = 0.0

    def emit(self, event) -> None:
        if event.kind == "start":
            self.front_peak_kb = _status_kb("VmHWM")
            self.rss_at_start_kb = _status_kb("VmRSS")
            Path("/proc/self/clear_refs").write_text("5")
            self.t_start = time.perf_counter()


def measure(log: str, frames: int | None, sets: list[str]) -> dict:
    import torch  # loaded (and its thread pool started) before the front end, so neither peak counts it

    from strep_core.config import RunConfig
    from strep_core.runner import run_input

    torch.ones(64, 64) @ torch.ones(64, 64)

    base: dict = {"method": "strep", "frames": None if frames is None else f"0:{frames}"}
    for item in sets:  # section.key=JSON, as `strep run --set`
        key, value = item.split("=", 1)
        section, name = key.split(".")
        base.setdefault(section, {})[name] = json.loads(value)
    cfg = RunConfig.build(**base)
    sink = _MemorySink()
    started = time.perf_counter()
    res = run_input(DATA / f"{log}-corrected.log.gz", cfg, sink=sink)
    wall = time.perf_counter() - started
    return {
        "log": log,
        "frames": res.metrics["frames"],
        "sets": sets,
        "batch_frames": res.config.optim.batch_frames,
        "iterations": res.iterations,
        "initial_ate": res.metrics["initial_ate"],
        "ate": res.metrics["ate"],
        "wall_seconds": wall,
        "front_seconds": res.timings["initial_guess"],
        "refine_seconds": res.timings.get("optimize"),
        "front_peak_mb": sink.front_peak_kb / 1024,
        "rss_at_refine_start_mb": sink.rss_at_start_kb / 1024,
        "refine_peak_mb": _status_kb("VmHWM") / 1024,
    }


def plot(rows: list[dict], png: Path) -> None:
    """Peak memory of the refinement above its start against scans (intel windows; aces and
    belgioioso whole as single points): rows labelled ``before*`` and ``after``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def rise(r: dict) -> float:
        return r["refine_peak_mb"] - r["rss_at_refine_start_mb"]

    fig, ax = plt.subplots(figsize=(7, 4.2))
    before = sorted((r for r in rows if r["label"].startswith("before")), key=lambda r: r["frames"])
    after = sorted((r for r in rows if r["label"] == "after" and r["log"] == "intel"), key=lambda r: r["frames"])
    # up to 256 frames "auto" is one batch: the same run as before (bitwise), so after = before there
    same = [r for r in before if r["frames"] <= 256 and r["log"] == "intel"]
    ax.plot([r["frames"] for r in before], [rise(r) for r in before], "o-", label="one batch of all frames (before)")
    ax.plot(
        [r["frames"] for r in same + after], [rise(r) for r in same + after], "s-", label="batch_frames=auto (after)"
    )
    for r in rows:
        if r["label"] == "after" and r["log"] != "intel":
            ax.plot(r["frames"], rise(r), "^", color="C2")
            below = r["frames"] < 400
            ax.annotate(
                f"{r['log']} (after)",
                (r["frames"], rise(r)),
                xytext=(-60 if below else 5, -14 if below else 6),
                textcoords="offset points",
                fontsize=8,
            )
    ax.plot(
        [r["frames"] for r in before],
        [r["front_peak_mb"] for r in before],
        "k--",
        label="pose-graph front end: whole process peak (torch loaded)",
    )
    ax.set_xlabel("scans (intel, the first N)")
    ax.set_ylabel("MB")
    ax.set_title("strep run, defaults: the refinement's peak memory above its start")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", default="intel")
    parser.add_argument("--frames", default="100,200,400,910", help="first N scans, comma separated; 'all'")
    parser.add_argument("--set", action="append", default=[], help="config override section.key=value")
    parser.add_argument("--label", default="")
    parser.add_argument("--out", type=Path, default=Path("/tmp/refine_memory.jsonl"))
    parser.add_argument("--plot", type=Path, help="plot this .jsonl instead of running")
    parser.add_argument("--png", type=Path, default=Path("docs/design/whole-logs-memory.png"))
    args = parser.parse_args()
    if args.plot is not None:
        rows = [json.loads(line) for line in args.plot.read_text().splitlines() if line.strip()]
        plot(rows, args.png)
        print(f"wrote {args.png}")
        return
    for n in args.frames.split(","):  # one window per process gives a clean peak: run one at a time
        row = {"label": args.label, **measure(args.log, None if n == "all" else int(n), args.set)}
        print(json.dumps(row), flush=True)
        with args.out.open("a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
