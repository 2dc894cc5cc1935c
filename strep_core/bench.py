"""``strep bench``: every method on the standard sequences, one table and one JSON.

Suites (``--suites``):

* ``v1_pose0``: DeepMapping's public 2D sequence (real file in the shared data), pixels;
* ``sim2d``: simulated 2D lidar like the paper's, 20 trajectories over 3 maps (seeded), pixels;
* ``carmen``: real laser logs, intel and aces windows 0:100 and 300:400, metres, from identity
  (the logs' odometry is dropped so every method starts from the same guess);
* ``sim3d``: simulated indoor depth like the paper's AVD setting, 16-frame trajectories, metres.

``--quick`` shrinks every suite (fewer sequences, frames and iterations) to finish in minutes.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from strep_core.config import RunConfig
from strep_core.sequence import Sequence

ALL_METHODS = ["identity", "icp", "multiway", "kiss", "deepmapping", "strep-nolink", "strep"]
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@dataclass(frozen=True)
class BenchCase:
    suite: str
    name: str
    load: Callable[[], Sequence]


def _v1_pose0(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.deepmapping import read_deepmapping

    path = data / "deepmapping_2d" / "v1_pose0.tar"
    yield BenchCase("v1_pose0", "v1_pose0", lambda: read_deepmapping(path))


def _sim2d(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.sim.lidar2d import simulate_2d

    # 20 trajectories over 3 maps, as in the paper (quick: 3 trajectories of 96 frames)
    count, frames = (3, 96) if quick else (20, 256)
    for i in range(count):
        map_seed = i % 3
        yield BenchCase(
            "sim2d",
            f"sim2d-m{map_seed}-t{i}",
            lambda i=i, m=map_seed: simulate_2d(1000 + i, frames=frames, map_seed=m),
        )


def _carmen(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.carmen import read_carmen

    windows = ["0:100"] if quick else ["0:100", "300:400"]
    for log in ("intel", "aces"):
        path = data / "carmen" / f"{log}-corrected.log.gz"
        for w in windows:

            def load(path: Path = path, w: str = w, log: str = log) -> Sequence:
                seq = read_carmen(path, frames=w)
                # same start for every method: identity (FACTS: classical tools from identity)
                return replace(seq, initial_poses=None, name=f"{log}[{w}]")

            yield BenchCase("carmen", f"{log}[{w}]", load)


def _sim3d(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.sim.depth3d import simulate_3d

    count = 2 if quick else 10
    for i in range(count):
        yield BenchCase("sim3d", f"sim3d-{i}", lambda i=i: simulate_3d(2000 + i, frames=16))


SUITES: dict[str, Callable[[Path, bool], Iterator[BenchCase]]] = {
    "v1_pose0": _v1_pose0,
    "sim2d": _sim2d,
    "carmen": _carmen,
    "sim3d": _sim3d,
}


def method_config(method: str, quick: bool, seq: Sequence) -> RunConfig:
    """The config a method runs with in the benchmark: defaults, fewer iterations in quick mode."""
    cfg = RunConfig(method=method)
    if quick:
        cfg = cfg.model_copy(update={"optim": cfg.optim.model_copy(update={"iterations": 60})})
    return cfg


def run_case(case: BenchCase, methods: list[str], quick: bool) -> list[dict[str, Any]]:
    from strep_core.methods import run

    seq = case.load()
    rows = []
    for m in methods:
        t0 = time.perf_counter()
        try:
            res = run(seq, method_config(m, quick, seq))
            row = {k: v for k, v in res.metrics.items() if isinstance(v, (int, float, str)) or v is None}
            row["status"] = "ok"
        except Exception as exc:  # a failing method is a result, not a crash of the benchmark
            row = {"method": m, "status": f"failed: {type(exc).__name__}: {exc}", "ate": None, "point_l2": None}
            row["wall_seconds"] = time.perf_counter() - t0
        row.update({"suite": case.suite, "case": case.name, "unit": seq.unit})
        rows.append(row)
    return rows


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and v is not None and math.isfinite(v) else math.nan


def summarize(rows: list[dict[str, Any]], methods: list[str]) -> list[dict[str, Any]]:
    """Mean ATE, point L2 and wall seconds per suite and method."""
    out = []
    for suite in dict.fromkeys(r["suite"] for r in rows):
        for m in methods:
            sel = [r for r in rows if r["suite"] == suite and r["method"] == m]
            if not sel:
                continue
            out.append(
                {
                    "suite": suite,
                    "method": m,
                    "cases": len(sel),
                    "mean_ate": float(np.nanmean([_num(r.get("ate")) for r in sel])),
                    "mean_point_l2": float(np.nanmean([_num(r.get("point_l2")) for r in sel])),
                    "mean_wall_seconds": float(np.nanmean([_num(r.get("wall_seconds")) for r in sel])),
                    "failed": sum(1 for r in sel if r["status"] != "ok"),
                }
            )
    return out


def format_table(rows: list[dict[str, Any]], summary: list[dict[str, Any]], methods: list[str]) -> str:
    """A markdown table: one row per case, ATE / point L2 / seconds per method, then means."""

    def cell(r: dict[str, Any] | None) -> str:
        if r is None:
            return "-"
        if r.get("status", "ok") != "ok":
            return "failed"
        return f"{_num(r.get('ate')):.3g} / {_num(r.get('point_l2')):.3g} / {_num(r.get('wall_seconds')):.3g}s"

    head = "| suite | case | unit | " + " | ".join(methods) + " |"
    lines = [head, "|" + "---|" * (3 + len(methods))]
    for suite, case in dict.fromkeys((r["suite"], r["case"]) for r in rows):
        by_m = {r["method"]: r for r in rows if r["suite"] == suite and r["case"] == case}
        unit = next(iter(by_m.values()))["unit"]
        lines.append(f"| {suite} | {case} | {unit} | " + " | ".join(cell(by_m.get(m)) for m in methods) + " |")
    for suite in dict.fromkeys(s["suite"] for s in summary):
        by_m = {s["method"]: s for s in summary if s["suite"] == suite}
        cells = []
        for m in methods:
            s = by_m.get(m)
            cells.append(
                "-"
                if s is None
                else f"**{s['mean_ate']:.3g}** / {s['mean_point_l2']:.3g} / {s['mean_wall_seconds']:.3g}s"
            )
        lines.append(f"| {suite} | **mean** | | " + " | ".join(cells) + " |")
    return "\n".join(lines)


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


def main(args: argparse.Namespace) -> int:
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
    cases = [c for s in suites for c in SUITES[s](data, args.quick)]
    rows: list[dict[str, Any]] = []
    started = time.perf_counter()
    for case in tqdm(cases, desc="bench", unit="seq"):
        rows.extend(run_case(case, methods, args.quick))
    summary = summarize(rows, methods)
    table = format_table(rows, summary, methods)
    report = {
        "machine": machine_info(),
        "quick": bool(args.quick),
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
    return 0
