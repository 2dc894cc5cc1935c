"""The learned methods from scratch on the benchmark's 2D sequences, resumable, in parallel.

Every (case, method) run of `strep bench --start scratch` (identity, no classical step, the
from-scratch profile) as one process of ``--jobs`` at a time with ``--threads`` torch threads,
each finished row appended to ``OUT/rows.jsonl`` at once, so an interrupted run resumes
where it stopped (rows already there are skipped). At the end it prints the benchmark's
table, the claims' counts (linked below no-link per sequence; DeepMapping failures above
100 px and what strep reaches there) and writes ``OUT/bench.json``.

    PYTHONPATH=. .venv/bin/python benchmarks/from_scratch.py --out runs/scratch \
        [--suites v1_pose0,sim2d] [--methods strep,strep-nolink,deepmapping] [--jobs 2] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path
from typing import Any

from strep_bench.bench import machine_info
from strep_bench.cases import DEFAULT_DATA, SUITES, run_case, summarize
from strep_bench.tables import format_table

FAILED_PX = 100.0  # claims 1-2: a run fails above this ATE (px), as in docs/reproduction.md


def _one(suite: str, index: int, method: str, data: str, threads: int) -> dict[str, Any]:
    case = replace(list(SUITES[suite](Path(data), False))[index], start="scratch")
    return run_case(case, [method], quick=False, threads=threads)[0]


def claims(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-sequence comparisons of the learned variants (ATE)."""
    by_case: dict[str, dict[str, float]] = {}
    for r in rows:
        if r.get("status") == "ok" and r.get("ate") is not None:
            by_case.setdefault(r["case"], {})[r["method"]] = float(r["ate"])
    both = {c: m for c, m in by_case.items() if "strep" in m and "strep-nolink" in m}
    dm = {c: m for c, m in by_case.items() if "strep" in m and "deepmapping" in m}
    return {
        "linked_below_nolink": sum(m["strep"] < m["strep-nolink"] for m in both.values()),
        "linked_vs_nolink_cases": len(both),
        "strep_at_most_10px": sum(m["strep"] <= 10.0 for m in by_case.values() if "strep" in m),
        "strep_cases": sum("strep" in m for m in by_case.values()),
        "deepmapping_failed": {c: m for c, m in dm.items() if m["deepmapping"] > FAILED_PX},
        "strep_below_deepmapping": sum(m["strep"] < m["deepmapping"] for m in dm.values()),
        "strep_vs_deepmapping_cases": len(dm),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--suites", default="v1_pose0,sim2d")
    ap.add_argument("--methods", default="strep,strep-nolink,deepmapping")
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "rows.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    done = {(r["suite"], r["case"], r["method"]) for r in rows}
    methods = args.methods.split(",")
    todo = []  # methods inner-most: every sequence gets all its methods before the next starts
    for suite in args.suites.split(","):
        for i, case in enumerate(SUITES[suite](Path(args.data), False)):
            todo += [(suite, i, m) for m in methods if (suite, case.name, m) not in done]
    started = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = {pool.submit(_one, s, i, m, args.data, args.threads): (s, i, m) for s, i, m in todo}
        for fut in as_completed(futures):
            row = fut.result()
            rows.append(row)
            with log.open("a") as fh:
                fh.write(json.dumps(row, default=str) + "\n")
            print(
                f"{row['case']} {row['method']}: ATE {row.get('ate')} in {row.get('wall_seconds', 0):.0f} s", flush=True
            )
    summary = summarize(rows, methods)
    report = {
        "machine": machine_info(),
        "start": "scratch",
        "wall_seconds_this_invocation": time.perf_counter() - started,
        "methods": methods,
        "rows": rows,
        "summary": summary,
        "claims": claims(rows),
    }
    (args.out / "bench.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    print(format_table(rows, summary, methods))
    print(json.dumps(report["claims"], default=str))


if __name__ == "__main__":
    main()
