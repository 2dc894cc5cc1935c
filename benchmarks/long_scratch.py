"""From scratch at any length (issue 33): the learned methods on simulated 2D sequences of N frames.

`strep generate 2d --frames N --seed S` sequences (the paper's motion), each run from identity
with every default (`strep run --start scratch`), one process per run, ``--jobs`` at a time.
Rows are appended to ``OUT/rows.jsonl`` as they finish (an interrupted run resumes); at the end
it prints a table (ATE per frames and method, time per frame) and writes ``OUT/long.json``.
For a windowed run (`strep_core.windows`) the rows also hold the joined poses' ATE before the
refinement, after the loops across windows (`strep_core.window_graph`) and the worst window's own ATE.

    PYTHONPATH=. python benchmarks/long_scratch.py --out runs/long --frames 512 1024 --seeds 0 1 2 3 4
    PYTHONPATH=. python benchmarks/long_scratch.py --out runs/long --frames 256 --methods strep strep-nolink
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np


def one(frames: int, seed: int, method: str, threads: int, overrides: dict[str, Any]) -> dict[str, Any]:
    """One run in this process; returns its row."""
    from strep_core.config import RunConfig, merge
    from strep_core.runner import run
    from strep_core.sim.lidar2d import simulate_2d

    seq = simulate_2d(seed, frames=frames)
    cfg = merge({"method": method, "start": "scratch", "threads": threads}, overrides)
    t0 = time.perf_counter()
    res = run(seq, RunConfig.model_validate(cfg))
    m = res.metrics
    keys = ("ate", "initial_ate", "joined_ate", "graph_ate", "window_ate_max", "windows", "window_loops", "iterations")
    row: dict[str, Any] = {"frames": frames, "seed": seed, "method": method, "device": res.config.device}
    row.update({k: m.get(k) for k in keys})
    row["wall_seconds"] = time.perf_counter() - t0
    return row


def _set(text: str) -> dict[str, Any]:
    key, _, value = text.partition("=")
    out: dict[str, Any] = {}
    node = out
    *path, last = key.split(".")
    for part in path:
        node = node.setdefault(part, {})
    node[last] = json.loads(value) if value[:1] in "0123456789-[{tfn" else value
    return out


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| frames | method | runs | ATE mean | ATE max | joined mean | graph mean | s / frame |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (frames, method), group in sorted(_groups(rows).items()):
        ate = np.array([r["ate"] for r in group], float)
        per = np.mean([r["wall_seconds"] / frames for r in group])
        stage = " | ".join(_mean(group, key) for key in ("joined_ate", "graph_ate"))
        lines.append(
            f"| {frames} | {method} | {len(group)} | {ate.mean():.2f} | {ate.max():.2f} | {stage} | {per:.3f} |"
        )
    return "\n".join(lines)


def _mean(group: list[dict[str, Any]], key: str) -> str:
    values = [r[key] for r in group if r.get(key) is not None]
    return f"{np.mean(values):.2f}" if values else "-"


def _groups(rows: list[dict[str, Any]]) -> dict[tuple[int, str], list[dict[str, Any]]]:
    out: dict[tuple[int, str], list[dict[str, Any]]] = {}
    for r in rows:
        if r.get("ate") is not None:
            out.setdefault((r["frames"], r["method"]), []).append(r)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--methods", nargs="+", default=["strep"])
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1, help="torch threads of each run")
    ap.add_argument("--set", action="append", default=[], help="config override, e.g. optim.iterations=500")
    args = ap.parse_args()
    overrides: dict[str, Any] = {}
    from strep_core.config import merge

    for text in args.set:
        overrides = merge(overrides, _set(text))
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "rows.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    done = {(r["frames"], r["seed"], r["method"]) for r in rows}
    todo = [
        (n, s, m)
        for n in sorted(args.frames, reverse=True)  # the longest first: the pool ends on short runs
        for s in args.seeds
        for m in args.methods
        if (n, s, m) not in done
    ]
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = [pool.submit(one, n, s, m, args.threads, overrides) for n, s, m in todo]
        for fut in as_completed(futures):
            row = fut.result()
            rows.append(row)
            with log.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(
                f"{row['frames']} s{row['seed']} {row['method']}: ATE {row['ate']:.2f} "
                f"(joined {row.get('joined_ate')}, graph {row.get('graph_ate')}) in {row['wall_seconds']:.0f} s",
                flush=True,
            )
    print(table(rows))
    (args.out / "long.json").write_text(json.dumps({"overrides": overrides, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
