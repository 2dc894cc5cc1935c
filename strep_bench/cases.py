"""The benchmark's cases: the standard sequences, each method's config on them, and `run_case`.

Suites (``--suites``):

* ``v1_pose0``: DeepMapping's public 2D sequence (real file in the shared data), pixels;
* ``sim2d``: simulated 2D lidar like the paper's, 20 trajectories over 3 maps (seeded), pixels;
* ``carmen``: real laser logs, the eight of the shared data: windows 0:100 and 300:400 (edmonton's
  340 scans: 300:340), and every whole log (``identity`` and ``multiway`` only: the planar-laser
  SLAM, docs/design/laser-slam.md); quick: intel, aces and belgioioso 0:100. Metres, from
  identity (the logs' odometry equals their corrected poses: the reader drops it);
* ``sim3d``: simulated indoor depth like the paper's AVD setting, 16-frame trajectories, metres
  (the probe picks the ``depth-turning`` profile);
* ``sevenscenes``: real Kinect depth (Microsoft 7-Scenes, frames 0-99 in the shared data),
  16-frame windows of every 4th frame (0:64:4, 16:80:4, 36:100:4) and of every frame (0:16,
  40:56), depth subsampled every 8 px (about 4,300 points a frame), from identity;
* ``bunny``: the 10 Stanford bunny range scans (views up to 180 degrees apart), voxel 2 mm
  (6,000 to 7,000 points a scan), once from identity and once from ``init="fpfh"``
  (`strep_core.globalreg`), every method alike; its rows are labelled ``bunny`` and
  ``bunny+fpfh`` so that each initial guess gets its own mean;
* ``lidar``: 20 consecutive scans of a hand-held solid-state Livox LiDAR (BALM, about 82,000
  points a scan, turns up to 29 degrees), from identity (quick: the first 10); the probe picks
  the ``lidar`` profile (docs/design/lidar.md).

On both real 3D suites learned methods run at most 100 iterations (`REAL3D_ITERATIONS`).

The real 3D suites (`POSE_ERROR_SUITES`) get a second table in mm and degrees with the
pairwise relative-pose errors (`strep_core.metrics.pairwise_errors`), which need no alignment:
their reference trajectories barely translate (7-Scenes windows: a few cm; the bunny scans:
all but four share one position), so only the map fixes a rigid alignment (as `point_l2` does).

``--quick`` shrinks every suite (fewer sequences, frames and iterations) to finish in minutes.

`run_case` runs the methods on one case: `strep_bench.bench` (``strep bench``) loops over the
cases, `strep_bench.ray_runner` spreads them over Ray, and `strep_bench.reproduce` reuses the
cases and `case_config` for the paper's claims. Every suite uses the defaults and the profile
the probe picks: no suite has constants of its own beyond its reader options.
"""

from __future__ import annotations

import math
import os
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
    methods: tuple[str, ...] | None = None  # only these of the requested methods (None: all)


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


CARMEN_LOGS = (
    "intel",
    "aces",
    "belgioioso",
    "acapulco",
    "edmonton",
    "freiburg-079",
    "freiburg-campus",
    "infinite-corridor",
)
WHOLE_LOG_METHODS = ("identity", "multiway")  # whole logs: the front and back end, not the learned refinement


def _carmen(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.carmen import read_carmen

    logs = CARMEN_LOGS[:3] if quick else CARMEN_LOGS
    for log in logs:
        path = data / "carmen" / f"{log}-corrected.log.gz"
        windows: list[str | None] = ["0:100"] if quick else ["0:100", "300:400", None]
        for w in windows:

            def load(path: Path = path, w: str | None = w, log: str = log) -> Sequence:
                # the reader drops these logs' odometry (it equals the corrected poses): every
                # method starts from identity, as `strep run LOG --frames W` does
                seq = read_carmen(path, frames=w)
                assert seq.initial_poses is None
                return replace(seq, name=f"{log}[{w or 'all'}]")

            methods = WHOLE_LOG_METHODS if w is None else None
            yield BenchCase("carmen", f"{log}[{w or 'all'}]", load, source=str(path), frames=w, methods=methods)


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


def _lidar(data: Path, quick: bool) -> Iterator[BenchCase]:
    from strep_core.io.folder import read_folder

    path = data / "lidar_balm"
    frames = "0:10" if quick else None

    def load() -> Sequence:
        return read_folder(path, frames=frames)

    yield BenchCase(
        "lidar", "lidar_balm" if frames is None else f"lidar_balm[{frames}]", load, source=str(path), frames=frames
    )


SUITES: dict[str, Callable[[Path, bool], Iterator[BenchCase]]] = {
    "v1_pose0": _v1_pose0,
    "sim2d": _sim2d,
    "carmen": _carmen,
    "sim3d": _sim3d,
    "sevenscenes": _sevenscenes,
    "bunny": _bunny,
    "lidar": _lidar,
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
    # the warm start's settings, whatever init the case or a plan sets (start auto with init
    # identity would be scratch)
    cfg = method_config(method, quick, seq).model_copy(update={"start": "pose-graph"})
    if case.init is not None:
        cfg = cfg.model_copy(update={"init": case.init})
    if case.data:
        cfg = cfg.model_copy(update={"data": type(cfg.data).model_validate(case.data)})
    if case.iterations is not None and cfg.optim.iterations > case.iterations:
        cfg = cfg.model_copy(update={"optim": cfg.optim.model_copy(update={"iterations": case.iterations})})
    return cfg


def _as_typed(source: str | None) -> str | None:
    """``source`` relative to the working directory (``../shared/data/...`` from the repository),
    as a user types it, so the recorded rows carry no machine's folders."""
    if source is None:
        return None
    try:
        return os.path.relpath(source)
    except ValueError:  # another drive (Windows)
        return source


def run_case(case: BenchCase, methods: list[str], quick: bool, threads: int | None = None) -> list[dict[str, Any]]:
    """Run each method on the case through the runner (`strep_core.runner.run`), the case read once;
    ``threads`` (torch CPU threads) overrides the configs' default."""
    from strep_core.runner import run

    seq = case.load()
    rows = []
    for m in methods if case.methods is None else [m for m in methods if m in case.methods]:
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
            row["input"] = _as_typed(case.source)
            row["config"] = {**res.config.model_dump(mode="json"), "frames": case.frames}
        except Exception as exc:  # a failing method is a result, not a crash of the benchmark
            row = {"method": m, "status": f"failed: {type(exc).__name__}: {exc}", "ate": None, "point_l2": None}
            row["wall_seconds"] = time.perf_counter() - t0
        row.update({"suite": case.suite, "case": case.name, "unit": seq.unit})
        rows.append(row)
    return rows


def as_number(v: Any) -> float:
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
    nums = [v for v in map(as_number, values) if math.isfinite(v)]
    return float(np.mean(nums)) if nums else None


POSE_KEYS = ("pair_rot_err_mean_deg", "pair_trans_err_mean")
