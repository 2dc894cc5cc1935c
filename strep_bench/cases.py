"""``strep bench``: every method on the standard sequences, one table and one JSON.

Suites (``--suites``):

* ``v1_pose0``: DeepMapping's public 2D sequence (real file in the shared data), pixels;
* ``sim2d``: simulated 2D lidar like the paper's, 20 trajectories over 3 maps (seeded), pixels;
* ``carmen``: real laser logs, intel, aces and belgioioso windows 0:100 and 300:400 (quick:
  0:100), metres, from identity (the logs' odometry equals their corrected poses: the reader
  drops it); the probe picks the ``laser-keyframes`` profile (`strep_core.profiles`);
* ``sim3d``: simulated indoor depth like the paper's AVD setting, 16-frame trajectories, metres
  (the probe picks the ``depth-turning`` profile);
* ``sevenscenes``: real Kinect depth (Microsoft 7-Scenes, frames 0-99 in the shared data),
  16-frame windows of every 4th frame (0:64:4, 16:80:4, 36:100:4) and of every frame (0:16,
  40:56), depth subsampled every 8 px (about 4,300 points a frame), from identity;
* ``bunny``: the 10 Stanford bunny range scans (views up to 180 degrees apart), voxel 2 mm
  (6,000 to 7,000 points a scan), once from identity and once from ``init="fpfh"``
  (`strep_core.globalreg`), every method alike; its rows are labelled ``bunny`` and
  ``bunny+fpfh`` so that each initial guess gets its own mean.

On both real 3D suites learned methods run at most 100 iterations (`REAL3D_ITERATIONS`).

The real 3D suites (`POSE_ERROR_SUITES`) get a second table in mm and degrees with the
pairwise relative-pose errors (`strep_core.metrics.pairwise_errors`), which need no alignment:
their reference trajectories barely translate (7-Scenes windows: a few cm; the bunny scans:
all but four share one position), so only the map fixes a rigid alignment (as `point_l2` does).

``--quick`` shrinks every suite (fewer sequences, frames and iterations) to finish in minutes.

`main` takes an optional ``runner`` (cases, methods, quick -> rows) in place of the loop over
`run_case`: ``strep bench --executor ray`` passes `app.bench_ray.run_cases_ray`, which runs every
(case, method) pair as one Ray task; rows, table and JSON are the same. Cluster code stays in
``app/``.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from strep_core.config import RunConfig
from strep_core.sequence import Sequence

ALL_METHODS = ["identity", "icp", "multiway", "kiss", "deepmapping", "strep-nolink", "strep"]
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@dataclass(frozen=True)
class BenchCase:
    """One sequence of a suite; ``init`` (a `RunConfig.init`) overrides every method's
    initial guess, ``iterations`` caps learned methods' optimiser iterations, ``data`` holds the
    reader options the loader used (recorded as `RunConfig.data`, so ``strep run`` with the saved
    config.json reads the same frames). Every other setting is the default, the profile chosen
    by the probe included (`strep_core.profiles`): no suite has constants of its own.
    ``start="scratch"`` (``strep bench --start scratch``) runs the learned methods from identity
    with no classical step and their from-scratch settings; ``init`` and ``iterations`` then
    apply to the classical methods only."""

    suite: str
    name: str
    load: Callable[[], Sequence]
    init: str | None = None
    iterations: int | None = None
    data: dict[str, Any] = field(default_factory=dict)
    start: str = "pose-graph"
    source: str | None = None  # the input a user gives `strep run` (None: generated in memory)
    frames: str | None = None  # the frame selection the loader applied


def _v1_pose0(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.deepmapping import read_deepmapping

    path = data / "deepmapping_2d" / "v1_pose0.tar"
    yield BenchCase("v1_pose0", "v1_pose0", lambda: read_deepmapping(path), source=str(path))


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
    for log in ("intel", "aces", "belgioioso"):
        path = data / "carmen" / f"{log}-corrected.log.gz"
        for w in windows:

            def load(path: Path = path, w: str = w, log: str = log) -> Sequence:
                # the reader drops these logs' odometry (it equals the corrected poses): every
                # method starts from identity, as `strep run LOG --frames W` does
                seq = read_carmen(path, frames=w)
                assert seq.initial_poses is None
                return replace(seq, name=f"{log}[{w}]")

            yield BenchCase("carmen", f"{log}[{w}]", load, source=str(path), frames=w)


def _sim3d(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.sim.depth3d import simulate_3d

    count = 2 if quick else 10
    for i in range(count):
        yield BenchCase("sim3d", f"sim3d-{i}", lambda i=i: simulate_3d(2000 + i, frames=16))


SEVENSCENES_STRIDE = 8  # 640 x 480 depth every 8 px: about 4,300 valid points a frame
REAL3D_ITERATIONS = 100  # learned methods on the real 3D suites (60 with --quick)
BUNNY_VOXEL = 0.002  # metres: 6,000 to 7,000 points a scan


def _sevenscenes(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.depth import read_depth_folder

    path = data / "7scenes"
    # 16 frames every 4th (start + 15 * 4 < 100) and 16 consecutive frames
    windows = ["0:64:4", "0:16"] if quick else ["0:64:4", "16:80:4", "36:100:4", "0:16", "40:56"]
    for w in windows:

        def load(w: str = w) -> Sequence:
            seq = read_depth_folder(path, frames=w, stride=SEVENSCENES_STRIDE)
            seq.name = f"7scenes[{w}]"
            return seq

        yield BenchCase(
            "sevenscenes",
            f"7scenes[{w}]",
            load,
            iterations=REAL3D_ITERATIONS,
            data={"stride": SEVENSCENES_STRIDE},
            source=str(path),
            frames=w,
        )


def _bunny(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.folder import read_conf

    path = data / "stanford_bunny" / "bun.conf"
    for init in ("identity", "fpfh"):

        def load(init: str = init) -> Sequence:
            seq = read_conf(path, voxel=BUNNY_VOXEL)
            seq.name = f"bunny[{init}]"
            return seq

        # one summary group per initial guess: "bunny" (identity) and "bunny+fpfh"
        suite = "bunny" if init == "identity" else f"bunny+{init}"
        yield BenchCase(
            suite,
            f"bunny[{init}]",
            load,
            init=init,
            iterations=REAL3D_ITERATIONS,
            data={"voxel": BUNNY_VOXEL},
            source=str(path),
        )


SUITES: dict[str, Callable[[Path, bool], Iterator[BenchCase]]] = {
    "v1_pose0": _v1_pose0,
    "sim2d": _sim2d,
    "carmen": _carmen,
    "sim3d": _sim3d,
    "sevenscenes": _sevenscenes,
    "bunny": _bunny,
}
POSE_ERROR_SUITES = ("sevenscenes", "bunny", "bunny+fpfh")  # row labels of the real 3D suites


def method_config(method: str, quick: bool, seq: Sequence) -> RunConfig:
    """The config a method runs with in the benchmark: defaults, fewer iterations in quick mode."""
    cfg = RunConfig(method=method)
    if quick:
        cfg = cfg.model_copy(update={"optim": cfg.optim.model_copy(update={"iterations": 60})})
    return cfg


QUICK_SCRATCH_ITERATIONS = 400  # --quick --start scratch: enough to form a trajectory from identity


def case_config(case: BenchCase, method: str, quick: bool, seq: Sequence) -> RunConfig:
    """`method_config` with the case's initial guess and iteration cap."""
    from strep_core.methods import get

    if case.start == "scratch" and get(method).learned:
        optim = {"iterations": QUICK_SCRATCH_ITERATIONS} if quick else {}
        return RunConfig.build(method=method, start="scratch", optim=optim, data=case.data)
    cfg = method_config(method, quick, seq)
    if case.init is not None:
        cfg = cfg.model_copy(update={"init": case.init})
    if case.data:
        cfg = cfg.model_copy(update={"data": type(cfg.data).model_validate(case.data)})
    if case.iterations is not None and cfg.optim.iterations > case.iterations:
        cfg = cfg.model_copy(update={"optim": cfg.optim.model_copy(update={"iterations": case.iterations})})
    return cfg


def run_case(case: BenchCase, methods: list[str], quick: bool, threads: int | None = None) -> list[dict[str, Any]]:
    """Run each method on the case; ``threads`` (torch CPU threads) overrides the configs' default."""
    from strep_core.methods import run

    seq = case.load()
    rows = []
    for m in methods:
        t0 = time.perf_counter()
        try:
            cfg = case_config(case, m, quick, seq)
            res = run(seq, cfg if threads is None else cfg.model_copy(update={"threads": threads}))
            row: dict[str, Any] = {
                k: v for k, v in res.metrics.items() if isinstance(v, (int, float, str)) or v is None
            }
            row["status"] = "ok"
            # what `strep run INPUT --config` needs to redo this row: every setting, the profile
            # the probe chose among them, the reader options and the frame selection
            row["input"] = case.source
            row["config"] = {**res.config.model_dump(mode="json"), "frames": case.frames}
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
                    # None (JSON null), not NaN, when every case failed: bench.json stays valid JSON
                    "mean_ate": _finite_mean([r.get("ate") for r in sel]),
                    "mean_point_l2": _finite_mean([r.get("point_l2") for r in sel]),
                    "mean_wall_seconds": _finite_mean([r.get("wall_seconds") for r in sel]),
                    "failed": sum(1 for r in sel if r["status"] != "ok"),
                }
            )
            if suite in POSE_ERROR_SUITES:
                out[-1].update({f"mean_{key}": _finite_mean([r.get(key) for r in sel]) for key in POSE_KEYS})
    return out


def _finite_mean(values: list[Any]) -> float | None:
    """Mean of the finite numbers among ``values``; ``None`` when there is none (valid JSON)."""
    nums = [v for v in map(_num, values) if math.isfinite(v)]
    return float(np.mean(nums)) if nums else None


POSE_KEYS = ("pair_rot_err_mean_deg", "pair_trans_err_mean")


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
                else f"**{_num(s['mean_ate']):.3g}** / {_num(s['mean_point_l2']):.3g} / "
                f"{_num(s['mean_wall_seconds']):.3g}s"
            )
        lines.append(f"| {suite} | **mean** | | " + " | ".join(cells) + " |")
    pose = format_pose_table(rows, summary, methods)
    return "\n".join(lines) + (f"\n\n{pose}" if pose else "")


def format_pose_table(rows: list[dict[str, Any]], summary: list[dict[str, Any]], methods: list[str]) -> str:
    """Markdown table of the real 3D suites (`POSE_ERROR_SUITES`, metres shown in mm).

    Cells: ATE mm / pairwise rotation error deg / pairwise translation error mm / point L2 mm
    (points aligned) / wall seconds; ``""`` when no row belongs to those suites.
    """
    sel = [r for r in rows if r["suite"] in POSE_ERROR_SUITES]
    if not sel:
        return ""

    def mm(v: Any, unit: str) -> float:
        return _num(v) * (1000.0 if unit == "m" else 1.0)

    def cell(r: dict[str, Any] | None) -> str:
        if r is None:
            return "-"
        if r.get("status", "ok") != "ok":
            return "failed"
        u = r.get("unit", "m")
        return (
            f"{mm(r.get('ate'), u):.3g} / {_num(r.get('pair_rot_err_mean_deg')):.3g}° / "
            f"{mm(r.get('pair_trans_err_mean'), u):.3g} / {mm(r.get('point_l2'), u):.3g} / "
            f"{_num(r.get('wall_seconds')):.3g}s"
        )

    lines = [
        "Real 3D: ATE mm / pairwise rotation error (mean, deg) / pairwise translation error (mean, mm) / "
        "point L2 mm (points aligned) / wall seconds",
        "",
        "| suite | case | " + " | ".join(methods) + " |",
        "|" + "---|" * (2 + len(methods)),
    ]
    for suite, case in dict.fromkeys((r["suite"], r["case"]) for r in sel):
        by_m = {r["method"]: r for r in sel if r["suite"] == suite and r["case"] == case}
        lines.append(f"| {suite} | {case} | " + " | ".join(cell(by_m.get(m)) for m in methods) + " |")
    for suite in dict.fromkeys(r["suite"] for r in sel):
        by_s = {s["method"]: s for s in summary if s["suite"] == suite}
        cells = []
        for m in methods:
            s = by_s.get(m)
            cells.append(
                "-"
                if s is None
                else f"**{1000 * _num(s['mean_ate']):.3g}** / {_num(s['mean_pair_rot_err_mean_deg']):.3g}° / "
                f"{1000 * _num(s['mean_pair_trans_err_mean']):.3g} / {1000 * _num(s['mean_point_l2']):.3g} / "
                f"{_num(s['mean_wall_seconds']):.3g}s"
            )
        lines.append(f"| {suite} | **mean** | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_docs(path: Path, table: str, report: dict[str, Any]) -> None:
    """Write the table with the machine and settings it came from into a markdown file."""
    m = report["machine"]
    mode = "quick" if report["quick"] else "full"
    text = (
        "# Benchmarks\n\n"
        f"Latest `strep bench{' --quick' if report['quick'] else ''}` ({mode} mode): {len(report['rows'])} runs in "
        f"{report['wall_seconds']:.0f} s on {m['platform']}, {m['cpu_count']} CPU cores, torch {m['torch']}"
        f"{', GPU ' + m['cuda'] if m['cuda'] else ', no GPU'}.\n\n"
        "Cells: ATE / point L2 (in the sequence unit: px or m) / wall seconds. "
        + (
            "Learned methods start from scratch (identity, no classical step). "
            if report.get("start") == "scratch"
            else "Learned methods start from the pose-graph (`multiway`) warm start; "
        )
        + "CARMEN windows start every method from identity; settings are the defaults with the profile the "
        "probe picks (`strep_core.profiles`).\n\n"
        f"{table}\n"
    )
    Path(path).write_text(text)


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
