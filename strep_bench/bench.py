"""``strep bench``: every method on the standard sequences, one table and one JSON.

`main` takes an optional ``runner`` (cases, methods, quick -> rows) in place of the loop over
`run_case`: ``--executor ray`` passes `strep_bench.ray_runner.run_cases_ray`; rows, table and
JSON are the same (`docs/scaling.md`).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from strep_bench.cases import ALL_METHODS, DEFAULT_DATA, SUITES, BenchCase, run_case, summarize
from strep_bench.tables import format_table, write_docs


def machine_info() -> dict[str, Any]:
    import os

    import torch

    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
    }


def main(
    args: argparse.Namespace, runner: Callable[[list[BenchCase], list[str], bool], list[dict[str, Any]]] | None = None
) -> int:
    """Run the benchmark; ``runner`` replaces the sequential loop over `run_case` (see the module docstring)."""
    from tqdm import tqdm

    from strep_core.errors import ConfigError
    from strep_core.methods import available

    methods = args.methods.split(",") if args.methods else ALL_METHODS
    known = available()
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise ConfigError(f"unknown methods {unknown}; choose from {list(known)}")
    suites = args.suites.split(",") if args.suites else list(SUITES)
    bad = [s for s in suites if s not in SUITES]
    if bad:
        raise ConfigError(f"unknown suites {bad}; choose from {list(SUITES)}")
    data = args.data or DEFAULT_DATA
    start = getattr(args, "start", None) or "pose-graph"
    cases = [replace(c, start=start) for s in suites for c in SUITES[s](data, args.quick)]
    rows: list[dict[str, Any]] = []
    started = time.perf_counter()
    executor = getattr(args, "executor", "local")
    if runner is not None:
        rows = runner(cases, methods, args.quick)
    else:
        for case in tqdm(cases, desc="bench", unit="seq"):
            rows.extend(run_case(case, methods, args.quick))
    summary = summarize(rows, methods)
    table = format_table(rows, summary, methods)
    report = {
        "machine": machine_info(),
        "quick": bool(args.quick),
        "start": start,
        "executor": executor,
        "wall_seconds": time.perf_counter() - started,
        "methods": methods,
        "rows": rows,
        "summary": summary,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(report, indent=2, allow_nan=False, default=str) + "\n")
    (out / "bench.md").write_text(table + "\n")
    print("cells: ATE / point L2 / wall seconds")
    print(table)
    print(f"wrote {out / 'bench.json'} and {out / 'bench.md'} in {report['wall_seconds']:.0f} s")
    if args.docs:
        write_docs(args.docs, table, report)
        print(f"updated {args.docs}")
    return 0
