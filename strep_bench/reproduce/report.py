"""``strep reproduce``: test each claim of the STREP paper with the benchmark's own runs.

The paper (Wang, Shi, Li, Fang: "Unsupervised Learning of Global Registration of Temporal
Sequence of Point Clouds") makes five claims that this implementation can test:

1. On 2D sequences where DeepMapping fails (ATE above 100 px), STREP succeeds (about 10 px).
2. There is no sequence where DeepMapping succeeds and STREP fails.
3. On real indoor 3D depth, STREP's mean and best-case ATE and point L2 beat DeepMapping's
   (here: 7-Scenes windows and the simulated AVD-like set).
4. Linked latents beat unlinked latents (the ablation) on both metrics.
5. With the network, ``w`` and the occupancy MLP trained on some sequences and frozen,
   re-optimising only the latents registers unseen sequences at least as well as optimising
   from scratch, in less time.

`PLANS` lists the runs each mode makes (``quick``: a couple of minutes, for CI; ``full``: about
45 minutes on a quiet 2-core CPU). Every run is seeded; each finished run's row is
cached in ``<out>/rows-<mode>.json`` so an interrupted run resumes where it stopped. `main`
writes the report (markdown, one table and verdict per claim, PNG figures next to it and a
JSON of every row). Verdicts are computed from the numbers by the rules in `THRESHOLDS`,
stated in the report; nothing in the report is written by hand.

The cases are the benchmark's (`strep_core.bench`): the same sequences, loaders and per-case
configs (`bench.case_config`), with the plan's seeds, initial guesses and iteration counts.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import math
import os
import re
import subprocess
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from strep_core.bench import DEFAULT_DATA, SUITES, BenchCase, case_config, machine_info
from strep_core.errors import StrepError
from strep_core.sequence import Sequence

# --------------------------------------------------------------------------------------------
# Thresholds of the verdicts (stated in the report)

FAIL_PX = 100.0  # claims 1-2: a 2D run fails above this ATE (the paper: baseline "more than 100")
SUCCESS_PX = 20.0  # claims 1-2: a 2D run succeeds at or below this ATE (twice the paper's "around 10")
TIE = 0.01  # claims 3-4: A beats B when A < B * (1 - TIE); within TIE either way is a tie
AS_WELL = 0.05  # claim 5: frozen registers "at least as well" when its ATE <= scratch ATE * (1 + AS_WELL)
THRESHOLDS = {"fail_px": FAIL_PX, "success_px": SUCCESS_PX, "tie": TIE, "as_well": AS_WELL}

VERDICTS = ("holds", "holds partly", "does not hold")
LEARNED = ("deepmapping", "strep-nolink", "strep")
LABEL = {"deepmapping": "DeepMapping", "strep-nolink": "STREP no-link", "strep": "STREP"}
SETTINGS = {
    "warm": ("icp", "ICP warm start (`init=icp`)"),
    "cold": ("identity", "from scratch (`start=scratch`: identity, no classical step, the from-scratch settings)"),
}
TRANSFER_MODES = ("scratch", "frozen", "frozen-short")


class ReproduceError(StrepError):
    """The report could not be produced or is incomplete."""


# --------------------------------------------------------------------------------------------
# Plans


@dataclass(frozen=True)
class Plan:
    """Which runs a mode makes. ``None`` iteration counts keep the benchmark's per-case counts
    (300, real 3D capped at `bench.REAL3D_ITERATIONS`)."""

    mode: str
    seeds_2d: tuple[int, ...]
    seeds_3d: tuple[int, ...]
    seeds_transfer: tuple[int, ...]
    v1_pose0_frames: int | None  # frames 0:N of v1_pose0; None: all 256; 0: left out
    sim2d_count: int  # the first N of the benchmark's sim2d trajectories
    sim2d_frames: int | None  # None: the benchmark's 256
    sevenscenes_windows: int  # the first N of the benchmark's 7-Scenes windows
    sim3d_count: int  # the first N of the benchmark's sim3d sequences
    iterations: int | None  # claims 1-4; None: the benchmark's
    transfer_train: int  # claim 5: training trajectories (map 0)
    transfer_test: int  # claim 5: unseen trajectories per test map (map 0 and map 1)
    transfer_frames: int
    transfer_iterations: int
    short_fraction: float = 1 / 3  # claim 5: frozen-short runs this fraction of the iterations


PLANS: dict[str, Plan] = {
    # about 45 minutes on a quiet 2-core CPU (see `estimate`), most of it the from-scratch 2D
    # runs (1000 iterations of 256 frames each): sized to fit a working session; each further
    # sim2d trajectory adds about 7 minutes, a second 3D seed about 11
    "full": Plan(
        mode="full",
        seeds_2d=(0,),
        seeds_3d=(0,),
        seeds_transfer=(0,),
        v1_pose0_frames=None,
        sim2d_count=3,
        sim2d_frames=None,
        sevenscenes_windows=3,
        sim3d_count=4,
        iterations=None,
        transfer_train=2,
        transfer_test=2,
        transfer_frames=256,
        transfer_iterations=300,
    ),
    # under a minute on a quiet 2-core CPU: short sequences, few iterations, two seeds
    "quick": Plan(
        mode="quick",
        seeds_2d=(0, 1),
        seeds_3d=(0, 1),
        seeds_transfer=(0,),
        v1_pose0_frames=48,
        sim2d_count=2,
        sim2d_frames=48,
        sevenscenes_windows=1,
        sim3d_count=1,
        iterations=20,
        transfer_train=1,
        transfer_test=1,
        transfer_frames=48,
        transfer_iterations=20,
    ),
    # the smallest plan that still fills every table (tests)
    "tiny": Plan(
        mode="tiny",
        seeds_2d=(0,),
        seeds_3d=(0,),
        seeds_transfer=(0,),
        v1_pose0_frames=0,
        sim2d_count=1,
        sim2d_frames=32,
        sevenscenes_windows=1,
        sim3d_count=0,
        iterations=10,
        transfer_train=1,
        transfer_test=1,
        transfer_frames=32,
        transfer_iterations=10,
    ),
}


@dataclass(frozen=True)
class Case:
    """A benchmark case with what the plan needs to know before loading it."""

    bench: BenchCase
    frames: int
    dim: int

    @property
    def name(self) -> str:
        return self.bench.name

    @property
    def suite(self) -> str:
        return self.bench.suite


def _first(it: Iterator[BenchCase], n: int) -> list[BenchCase]:
    return [c for _, c in zip(range(n), it, strict=False)]


def cases_2d(plan: Plan, data: Path) -> list[Case]:
    """v1_pose0 and the first sim2d trajectories of the benchmark (px)."""
    from strep_core.sim.lidar2d import simulate_2d

    out = []
    if plan.v1_pose0_frames != 0:
        (v1,) = _first(SUITES["v1_pose0"](data, False), 1)
        if plan.v1_pose0_frames is not None:
            n = plan.v1_pose0_frames

            def load_v1(load: Callable[[], Sequence] = v1.load, n: int = n) -> Sequence:
                seq = load().select(f"0:{n}")
                seq.name = f"v1_pose0[0:{n}]"
                return seq

            v1 = replace(v1, name=f"v1_pose0[0:{n}]", load=load_v1)
        out.append(Case(v1, plan.v1_pose0_frames or 256, 2))
    if plan.sim2d_frames is None:
        out += [Case(c, 256, 2) for c in _first(SUITES["sim2d"](data, False), plan.sim2d_count)]
    else:
        # the benchmark's trajectories (seed 1000 + i on map i % 3), shortened
        for i in range(plan.sim2d_count):
            m, f = i % 3, plan.sim2d_frames
            load = lambda i=i, m=m, f=f: simulate_2d(1000 + i, frames=f, map_seed=m)  # noqa: E731
            out.append(Case(BenchCase("sim2d", f"sim2d-m{m}-t{i}", load), f, 2))
    return out


def cases_3d(plan: Plan, data: Path) -> list[Case]:
    """The first 7-Scenes windows and sim3d sequences of the benchmark (16 frames, metres)."""
    out = [Case(c, 16, 3) for c in _first(SUITES["sevenscenes"](data, False), plan.sevenscenes_windows)]
    out += [Case(c, 16, 3) for c in _first(SUITES["sim3d"](data, False), plan.sim3d_count)]
    return out


def cases_transfer(plan: Plan) -> dict[str, list[Case]]:
    """Claim 5: training trajectories on map 0, unseen ones on map 0 and on map 1."""
    from strep_core.sim.lidar2d import simulate_2d

    f = plan.transfer_frames

    def make(role: str, base: int, m: int, n: int) -> list[Case]:
        return [
            Case(
                BenchCase(
                    f"transfer-{role}",
                    f"sim2d-s{base + j}-m{m}",
                    lambda s=base + j, m=m: simulate_2d(s, frames=f, map_seed=m),
                ),
                f,
                2,
            )
            for j in range(n)
        ]

    return {
        "train": make("train", 5000, 0, plan.transfer_train),
        "same-map": make("same-map", 5100, 0, plan.transfer_test),
        "other-map": make("other-map", 5200, 1, plan.transfer_test),
    }


@dataclass(frozen=True)
class RunSpec:
    """One run of the plan; `key` identifies its cached row."""

    claim: str  # "2d", "3d" or "transfer"
    case: Case = field(compare=False)
    method: str
    setting: str  # warm | cold | train | scratch | frozen | frozen-short
    init: str
    seed: int
    iterations: int | None  # None: the benchmark's
    model_in: str | None = None  # claim 5: model file to start from (relative to the out folder)
    model_out: str | None = None
    freeze: bool = False

    @property
    def key(self) -> str:
        it = "bench" if self.iterations is None else str(self.iterations)
        return (
            f"{self.claim}|{self.case.suite}|{self.case.name}|{self.case.frames}f|{self.method}|{self.setting}"
            f"|{self.init}|seed{self.seed}|{it}it"
        )

    def planned_iterations(self) -> int:
        from strep_core.config import SCRATCH_PROFILE, OptimConfig

        if self.setting == "cold":  # from scratch: the profile's count, not the case's warm-start cap
            n = int(SCRATCH_PROFILE["optim"]["iterations"])
            return n if self.iterations is None else min(n, self.iterations)
        n = OptimConfig().iterations
        if self.case.bench.iterations is not None:
            n = min(n, self.case.bench.iterations)
        return n if self.iterations is None else min(n, self.iterations)


def build_runs(plan: Plan, data: Path) -> list[RunSpec]:
    """Every run of a plan, grouped by sequence (each sequence is loaded once)."""
    runs: list[RunSpec] = []
    # claims 1, 2 and 4 in 2D: the three learned methods warm and cold (from scratch)
    for case in cases_2d(plan, data):
        for setting, (init, _) in SETTINGS.items():
            for m in LEARNED:
                runs += [RunSpec("2d", case, m, setting, init, s, plan.iterations) for s in plan.seeds_2d]
    # claims 3 and 4: the three learned methods on real and simulated 3D depth, warm and cold
    for case in cases_3d(plan, data):
        for setting, (init, _) in SETTINGS.items():
            for m in LEARNED:
                runs += [RunSpec("3d", case, m, setting, init, s, plan.iterations) for s in plan.seeds_3d]
    # claim 5: per seed, train a chain over the training trajectories, then test frozen vs scratch
    tr = cases_transfer(plan)
    n, short = plan.transfer_iterations, max(1, round(plan.transfer_iterations * plan.short_fraction))
    for s in plan.seeds_transfer:
        prev = None
        for j, case in enumerate(tr["train"]):
            out = f"models/{plan.mode}-seed{s}-step{j}.pt"
            runs.append(RunSpec("transfer", case, "strep", "train", "icp", s, n, model_in=prev, model_out=out))
            prev = out
        for group in ("same-map", "other-map"):
            for case in tr[group]:
                runs.append(RunSpec("transfer", case, "strep", "scratch", "icp", s, n))
                runs.append(RunSpec("transfer", case, "strep", "frozen", "icp", s, n, model_in=prev, freeze=True))
                runs.append(
                    RunSpec("transfer", case, "strep", "frozen-short", "icp", s, short, model_in=prev, freeze=True)
                )
    return runs


# --------------------------------------------------------------------------------------------
# Cost model (seconds on a quiet 2-core CPU; measured with 2 torch threads)

_ITER_PER_FRAME = {2: 4.2e-4, 3: 1.5e-3}  # learned optimiser, per frame and iteration
_ICP_PER_FRAME = {2: 4e-3, 3: 0.1}  # the ICP warm start, per frame
_LOAD = {2: 0.3, 3: 1.0}  # loading or simulating a sequence
_OVERHEAD = 0.3  # per run: metrics, final pass


def estimate_run(spec: RunSpec) -> float:
    d, k = spec.case.dim, spec.case.frames
    it = spec.planned_iterations() * k * _ITER_PER_FRAME[d] * (0.8 if spec.freeze else 1.0)
    warm = _ICP_PER_FRAME[d] * k if spec.init == "icp" else 0.0
    return it + warm + _OVERHEAD


def estimate(runs: list[RunSpec]) -> dict[str, float]:
    """Estimated seconds per claim group and in total (loading each sequence once)."""
    out: dict[str, float] = {}
    seen: set[tuple[str, str]] = set()
    for r in runs:
        load = 0.0
        if (r.case.suite, r.case.name) not in seen:
            seen.add((r.case.suite, r.case.name))
            load = _LOAD[r.case.dim]
        out[r.claim] = out.get(r.claim, 0.0) + estimate_run(r) + load
    out["total"] = sum(out.values())
    return out


# --------------------------------------------------------------------------------------------
# Running


def _code_version() -> str | None:
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "strep_core"], cwd=root, capture_output=True, text=True, timeout=10
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + ("+dirty" if dirty else "")) or None


def execute(spec: RunSpec, seq: Sequence, out: Path) -> dict[str, Any]:
    """Run one spec on its loaded sequence and return its row (never raises for a failed run)."""
    from strep_core.methods import run
    from strep_core.optimize import save_model

    t0 = time.perf_counter()
    row: dict[str, Any] = {
        "key": spec.key,
        "claim": spec.claim,
        "suite": spec.case.suite,
        "case": spec.case.name,
        "method": spec.method,
        "setting": spec.setting,
        "init": spec.init,
        "seed": spec.seed,
        "unit": seq.unit,
        "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    try:
        bench = spec.case.bench
        if spec.setting == "cold":
            bench = dataclasses.replace(bench, start="scratch")
        cfg = case_config(bench, spec.method, False, seq)
        optim = cfg.optim
        if spec.iterations is not None and spec.iterations < optim.iterations:
            optim = optim.model_copy(update={"iterations": spec.iterations})
        cfg = cfg.model_copy(
            update={
                "init": spec.init,
                "seed": spec.seed,
                "optim": optim,
                "from_model": str(out / spec.model_in) if spec.model_in else None,
                "freeze": spec.freeze,
            }
        )
        res = run(seq, cfg)
        m = res.metrics
        keep = ("ate", "point_l2", "initial_ate", "wall_seconds", "iterations", "frames", "points", "initial_guess")
        row.update({k: m.get(k) for k in keep})
        row.update({k: v for k, v in m.items() if k.startswith("pair_") and isinstance(v, (int, float))})
        row["optimize_seconds"] = res.timings.get("optimize")
        row["init_seconds"] = res.timings.get("initial_guess")
        row["history"] = [
            [h["iteration"], h.get("ate"), h.get("elapsed"), h.get("losses", {}).get("total")] for h in res.history
        ]
        if spec.model_out:
            path = out / spec.model_out
            path.parent.mkdir(parents=True, exist_ok=True)
            save_model(res.artifacts["model"], path)
        row["status"] = "ok"
    except Exception as exc:  # a failing run is a result (reported), not a crash of the report
        row.update({"status": f"failed: {type(exc).__name__}: {exc}", "ate": None, "point_l2": None})
    row["run_seconds"] = time.perf_counter() - t0
    return row


class RowCache:
    """Finished rows by key in one JSON file, rewritten atomically after every run."""

    def __init__(self, path: Path, fresh: bool = False) -> None:
        self.path = path
        self.rows: dict[str, dict[str, Any]] = {}
        if path.exists() and not fresh:
            try:
                self.rows = {r["key"]: r for r in json.loads(path.read_text())["rows"]}
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise ReproduceError(f"cannot read the cache {path}: {exc} (remove it or pass --fresh)") from exc

    def get(self, spec: RunSpec, out: Path) -> dict[str, Any] | None:
        row = self.rows.get(spec.key)
        if row is None or row.get("status") != "ok":
            return None  # failed runs are retried
        if spec.model_out and not (out / spec.model_out).exists():
            return None  # a training run whose model is gone runs again
        return row

    def put(self, row: dict[str, Any]) -> None:
        self.rows[row["key"]] = row
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"rows": list(self.rows.values())}, allow_nan=False, default=_json_default))
        os.replace(tmp, self.path)


def _json_default(v: Any) -> Any:
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return str(v)


def run_plan(
    runs: list[RunSpec], out: Path, cache: RowCache, *, progress: bool = True
) -> tuple[list[dict[str, Any]], int]:
    """Run (or take from the cache) every spec; returns the rows in plan order and how many ran."""
    from tqdm import tqdm

    code = _code_version()

    est = [estimate_run(r) for r in runs]
    rows: list[dict[str, Any]] = []
    ran = 0
    loaded: tuple[tuple[str, str], Sequence] | None = None
    with tqdm(total=round(sum(est)), desc="reproduce", unit="s(est)", disable=not progress, dynamic_ncols=True) as bar:
        cumulative = np.cumsum(est)
        for i, spec in enumerate(runs):
            bar.set_postfix_str(f"run {i + 1}/{len(runs)} {spec.method} {spec.setting} {spec.case.name}")
            row = cache.get(spec, out)
            if row is None:
                ident = (spec.case.suite, spec.case.name)
                if loaded is None or loaded[0] != ident:
                    loaded = (ident, spec.case.bench.load())
                row = execute(spec, loaded[1], out)
                row["code"] = code
                cache.put(row)
                ran += 1
                if row["status"] != "ok":
                    tqdm.write(f"run {spec.key} {row['status']}")
            rows.append(row)
            bar.update(round(float(cumulative[i])) - bar.n)
    return rows, ran


# --------------------------------------------------------------------------------------------
# Statistics


def _ok(rows: Iterable[dict[str, Any]], **where: Any) -> list[dict[str, Any]]:
    return [r for r in rows if r.get("status") == "ok" and all(r.get(k) == v for k, v in where.items())]


def _val(r: dict[str, Any], metric: str, display_mm: bool = False) -> float:
    v = r.get(metric)
    if not isinstance(v, (int, float)) or not math.isfinite(v):
        return math.nan
    return float(v) * (1000.0 if display_mm and r.get("unit") == "m" else 1.0)


def _mean_std(values: list[float]) -> tuple[float, float, int]:
    vals = [v for v in values if math.isfinite(v)]
    if not vals:
        return math.nan, math.nan, 0
    return float(np.mean(vals)), float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0, len(vals)


def over_seeds(
    rows: list[dict[str, Any]], metric: str, agg: Callable[[list[float]], float] = np.mean, mm: bool = False
) -> tuple[float, float, int]:
    """``agg`` over the sequences of each seed, then mean and sample std over seeds."""
    per_seed: dict[int, list[float]] = {}
    for r in rows:
        per_seed.setdefault(r["seed"], []).append(_val(r, metric, mm))
    stats = [
        float(agg([v for v in vals if math.isfinite(v)])) for vals in per_seed.values() if any(map(math.isfinite, vals))
    ]
    return _mean_std(stats)


def per_case_mean(rows: list[dict[str, Any]], metric: str, mm: bool = False) -> dict[str, float]:
    """Mean over seeds for every case (in first-seen order)."""
    out: dict[str, list[float]] = {}
    for r in rows:
        out.setdefault(r["case"], []).append(_val(r, metric, mm))
    return {c: _mean_std(v)[0] for c, v in out.items()}


def _g(v: float) -> str:
    if not math.isfinite(v):
        return "-"
    return f"{v:.3g}" if abs(v) < 1e5 else f"{v:.3e}"


def pm(stat: tuple[float, float, int]) -> str:
    m, s, n = stat
    if n == 0:
        return "-"
    return _g(m) if n == 1 else f"{_g(m)} ± {s:.2g}"


def compare(a: float, b: float) -> str:
    """``"better"`` when a < b by more than `TIE` (relative), ``"worse"``, ``"tie"`` or ``"n/a"``."""
    if not (math.isfinite(a) and math.isfinite(b)):
        return "n/a"
    if a < b * (1 - TIE):
        return "better"
    if a > b * (1 + TIE):
        return "worse"
    return "tie"


def _count_verdict(won: int, total: int) -> str:
    if total == 0 or won * 2 < total:
        return "does not hold"
    return "holds" if won == total else "holds partly"


# --------------------------------------------------------------------------------------------
# Claims: each returns markdown, a verdict and a reason


@dataclass
class ClaimReport:
    number: int
    title: str
    body: str
    verdict: str
    reason: str
    figure: str | None = None


def _sequences(rows: list[dict[str, Any]]) -> str:
    """``name (K frames)`` of every case in the rows, in order."""
    seen = {r["case"]: r.get("frames") for r in rows if r.get("status") == "ok"}
    return ", ".join(f"{c} ({k} frames)" for c, k in seen.items())


def _table(head: list[str], rows: list[list[str]]) -> str:
    assert all(len(r) == len(head) for r in rows), (head, [r for r in rows if len(r) != len(head)])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _trials_2d(rows: list[dict[str, Any]], setting: str) -> list[tuple[str, int, float, float]]:
    """(case, seed, DeepMapping ATE, STREP ATE) for every 2D trial run by both methods."""
    dm = {(r["case"], r["seed"]): r for r in _ok(rows, claim="2d", setting=setting, method="deepmapping")}
    st = {(r["case"], r["seed"]): r for r in _ok(rows, claim="2d", setting=setting, method="strep")}
    return [(c, s, _val(dm[c, s], "ate"), _val(st[c, s], "ate")) for (c, s) in dm if (c, s) in st]


def claim_2d_table(rows: list[dict[str, Any]]) -> str:
    """Per sequence and setting: initial ATE and each method's ATE (mean ± std over seeds)."""
    out = []
    for setting in SETTINGS:
        sel = _ok(rows, claim="2d", setting=setting)
        for case in dict.fromkeys(r["case"] for r in sel):
            cells = [
                setting,
                case,
                pm(_mean_std([_val(r, "initial_ate") for r in _ok(sel, case=case, method="strep")])),
            ]
            for m in LEARNED:
                rs = _ok(sel, case=case, method=m)
                if not rs:
                    cells.append("-")
                    continue
                ates = [_val(r, "ate") for r in rs]
                fails = sum(a > FAIL_PX for a in ates)
                wins = sum(a <= SUCCESS_PX for a in ates)
                cells.append(f"{pm(_mean_std(ates))} ({wins}/{len(ates)} ok, {fails} failed)")
            out.append(cells)
    return _table(["setting", "sequence", "start ATE px", *[f"{LABEL[m]} ATE px" for m in LEARNED]], out)


def claim1(rows: list[dict[str, Any]]) -> ClaimReport:
    table_rows = []
    failed_total = rescued_total = 0
    rescued_ates: list[float] = []
    for setting in SETTINGS:
        trials = _trials_2d(rows, setting)
        failed = [t for t in trials if t[2] > FAIL_PX]
        rescued = [t for t in failed if t[3] <= SUCCESS_PX]
        failed_total += len(failed)
        rescued_total += len(rescued)
        rescued_ates += [t[3] for t in rescued]
        table_rows.append(
            [
                setting,
                str(len(trials)),
                str(len(failed)),
                str(len(rescued)),
                pm(_mean_std([t[2] for t in failed])),
                pm(_mean_std([t[3] for t in failed])),
            ]
        )
    table = _table(
        [
            "setting",
            "trials (sequence x seed)",
            f"DeepMapping fails (> {FAIL_PX:g} px)",
            f"of those STREP succeeds (<= {SUCCESS_PX:g} px)",
            "DeepMapping ATE px on its failures",
            "STREP ATE px on the same trials",
        ],
        table_rows,
    )
    if failed_total == 0:
        verdict, reason = (
            "does not hold",
            f"not reproduced: DeepMapping never fails (ATE > {FAIL_PX:g} px) in these runs, so there is no "
            "failure for STREP to rescue",
        )
    elif rescued_total == failed_total:
        verdict, reason = (
            "holds",
            (
                f"STREP succeeds on all {failed_total} trials where DeepMapping fails "
                f"(mean {_g(float(np.mean(rescued_ates)))} px)"
            ),
        )
    elif rescued_total > 0:
        verdict, reason = "holds partly", f"STREP succeeds on {rescued_total} of {failed_total} DeepMapping failures"
    else:
        verdict, reason = (
            "does not hold",
            (f"STREP succeeds on none of the {failed_total} trials where DeepMapping fails: it fails there too"),
        )
    body = (
        "Data: DeepMapping's public v1_pose0 and the benchmark's simulated 2D lidar trajectories (map pixels, "
        "the paper's units). Each sequence is run by DeepMapping, STREP and STREP no-link (claim 4) under both "
        "settings, with every seed. Sequences: "
        f"{_sequences(_ok(rows, claim='2d'))}.\n\n"
        f"Per sequence (ATE mean ± std over seeds; 'ok' = at most {SUCCESS_PX:g} px, 'failed' = above "
        f"{FAIL_PX:g} px; start ATE = the initial guess the learned methods correct):\n\n"
        f"{claim_2d_table(rows)}\n\nThe claim's test:\n\n{table}"
    )
    return ClaimReport(
        1, "On 2D sequences where DeepMapping fails, STREP succeeds", body, verdict, reason, "claim1_2d_ate.png"
    )


def claim2(rows: list[dict[str, Any]]) -> ClaimReport:
    table_rows = []
    soft = strict = 0
    examples: list[str] = []
    for setting in SETTINGS:
        trials = _trials_2d(rows, setting)
        dm_ok = [t for t in trials if t[2] <= SUCCESS_PX]
        st_bad = [t for t in dm_ok if t[3] > SUCCESS_PX]
        st_fail = [t for t in dm_ok if t[3] > FAIL_PX]
        soft += len(st_bad)
        strict += len(st_fail)
        examples += [f"{c} seed {s} ({setting}: {_g(a)} vs {_g(b)} px)" for c, s, a, b in st_bad[:3]]
        table_rows.append([setting, str(len(trials)), str(len(dm_ok)), str(len(st_bad)), str(len(st_fail))])
    table = _table(
        [
            "setting",
            "trials",
            f"DeepMapping succeeds (<= {SUCCESS_PX:g} px)",
            f"of those STREP does not succeed (> {SUCCESS_PX:g} px)",
            f"of those STREP fails (> {FAIL_PX:g} px)",
        ],
        table_rows,
    )
    if soft == 0:
        verdict, reason = "holds", "on every trial where DeepMapping succeeds, STREP succeeds too"
    elif strict == 0:
        verdict, reason = (
            "holds partly",
            (
                f"STREP never fails where DeepMapping succeeds, but misses {SUCCESS_PX:g} px on {soft} such trial(s): "
                + "; ".join(examples)
            ),
        )
    else:
        verdict, reason = (
            "does not hold",
            (f"STREP fails (> {FAIL_PX:g} px) on {strict} trial(s) where DeepMapping succeeds: " + "; ".join(examples)),
        )
    body = (
        "Data: the same runs as claim 1 (the per-sequence table and figure are there). A counterexample is a trial "
        "(sequence, seed) where DeepMapping succeeds and STREP does not.\n\n" + table
    )
    return ClaimReport(2, "No sequence where DeepMapping succeeds and STREP fails", body, verdict, reason)


def _groups_3d(rows: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
    """(suite, setting, label) of the 3D groups present."""
    out = []
    for suite, name in (("sevenscenes", "7-Scenes"), ("sim3d", "sim3d")):
        for setting in SETTINGS:
            if _ok(rows, claim="3d", suite=suite, setting=setting):
                out.append((suite, setting, f"{name} {setting}"))
    return out


def claim3(rows: list[dict[str, Any]]) -> ClaimReport:
    table_rows = []
    won = total = 0
    lost: list[str] = []
    for suite, setting, label in _groups_3d(rows):
        sel = _ok(rows, claim="3d", suite=suite, setting=setting)
        stats = {}
        for m in ("deepmapping", "strep"):
            rs = _ok(sel, method=m)
            stats[m] = {
                "mean ATE": over_seeds(rs, "ate", np.mean, mm=True),
                "best ATE": over_seeds(rs, "ate", np.min, mm=True),
                "mean L2": over_seeds(rs, "point_l2", np.mean, mm=True),
                "best L2": over_seeds(rs, "point_l2", np.min, mm=True),
            }
            n_cases = len({r["case"] for r in rs})
            table_rows.append(
                [
                    label,
                    LABEL[m],
                    str(n_cases),
                    pm(over_seeds(rs, "initial_ate", mm=True)),
                    *[pm(v) for v in stats[m].values()],
                    pm(over_seeds(rs, "wall_seconds")),
                ]
            )
        results = []
        for k in stats["strep"]:
            c = compare(stats["strep"][k][0], stats["deepmapping"][k][0])
            if c != "n/a":
                total += 1
                won += c == "better"
                if c != "better":
                    lost.append(f"{label} {k} ({c})")
            results.append(f"{k}: {c}")
        table_rows.append([label, "STREP vs DeepMapping", "", "", *[r.split(": ")[1] for r in results], ""])
    table = _table(
        [
            "group",
            "method",
            "sequences",
            "start ATE mm",
            "mean ATE mm",
            "best ATE mm",
            "mean point L2 mm",
            "best point L2 mm",
            "wall s",
        ],
        table_rows,
    )
    verdict = _count_verdict(won, total)
    reason = f"STREP beats DeepMapping in {won} of {total} comparisons (4 per group)" + (
        "; not in: " + ", ".join(lost) if lost else ""
    )
    body = (
        "Data: real Kinect depth (7-Scenes windows of 16 frames, the closest stand-in here for the paper's AVD "
        "trajectories) and the benchmark's simulated AVD-like depth sequences (16 frames), both settings, every "
        f"seed. Sequences: {_sequences(_ok(rows, claim='3d'))}. "
        "'start' is the mean ATE of the initial guess (the ICP warm start or identity). "
        "'best' is the paper's lower bound: the smallest error over the sequences. Values are computed per "
        "seed (mean or minimum over the sequences), then shown as mean ± std over seeds; point L2 is the mean "
        f"distance of every point from its true place. 'better' means lower by more than {TIE:.0%}.\n\n" + table
    )
    return ClaimReport(
        3,
        "On indoor 3D depth STREP beats DeepMapping (mean and best case, ATE and point L2)",
        body,
        verdict,
        reason,
        "claim3_3d.png",
    )


def _groups_ablation(rows: list[dict[str, Any]]) -> list[tuple[dict[str, Any], str]]:
    out = [({"claim": "3d", "suite": s, "setting": st}, label) for s, st, label in _groups_3d(rows)]
    for setting in SETTINGS:
        if _ok(rows, claim="2d", setting=setting, method="strep-nolink"):
            out.append(({"claim": "2d", "setting": setting}, f"2D {setting}"))
    return out


def claim4(rows: list[dict[str, Any]]) -> ClaimReport:
    table_rows = []
    won = total = 0
    lost: list[str] = []
    for where, label in _groups_ablation(rows):
        unit = "mm" if where["claim"] == "3d" else "px"
        link, nolink = _ok(rows, method="strep", **where), _ok(rows, method="strep-nolink", **where)
        pair = {(r["case"], r["seed"]): r for r in nolink}
        cells_cmp = []
        for metric in ("ate", "point_l2"):
            a = over_seeds(link, metric, mm=True)[0]
            b = over_seeds(nolink, metric, mm=True)[0]
            c = compare(a, b)
            if c != "n/a":
                total += 1
                won += c == "better"
                if c != "better":
                    lost.append(f"{label} {metric} ({c})")
            paired = [(r, pair[r["case"], r["seed"]]) for r in link if (r["case"], r["seed"]) in pair]
            wins = sum(_val(x, metric) < _val(y, metric) for x, y in paired)
            cells_cmp.append(f"{c} ({wins}/{len(paired)} paired runs lower)")
        for m, rs in (("strep", link), ("strep-nolink", nolink)):
            table_rows.append(
                [
                    f"{label} ({unit})",
                    LABEL[m],
                    str(len(rs)),
                    pm(over_seeds(rs, "ate", mm=True)),
                    pm(over_seeds(rs, "point_l2", mm=True)),
                ]
            )
        table_rows.append([f"{label} ({unit})", "linked vs no-link", "", *cells_cmp])
    table = _table(["group", "latents", "runs", "mean ATE", "mean point L2"], table_rows)
    verdict = _count_verdict(won, total)
    reason = f"linked latents beat unlinked ones in {won} of {total} comparisons (ATE and point L2 per group)" + (
        "; not in: " + ", ".join(lost) if lost else ""
    )
    body = (
        "Data: `strep` (latents linked by w) and `strep-nolink` (the paper's ablation baseline: per-frame latents, "
        "no link) on the same sequences with the same seeds (the seed draws the same shared networks for both), "
        "3D groups as in claim 3 (the paper's ablation is on AVD) and the 2D sequences in both settings. "
        f"Mean ± std over seeds; 'better' means lower by more than {TIE:.0%}; paired runs: same sequence and seed.\n\n"
        + table
    )
    return ClaimReport(4, "Linked latents beat unlinked latents", body, verdict, reason, "claim4_ablation.png")


def claim5(rows: list[dict[str, Any]], plan: Plan) -> ClaimReport:
    table_rows = []
    holds_groups = []
    reasons = []
    train = _ok(rows, claim="transfer", setting="train")
    for group in ("same-map", "other-map"):
        stats = {}
        for mode in TRANSFER_MODES:
            rs = _ok(rows, claim="transfer", suite=f"transfer-{group}", setting=mode)
            stats[mode] = (over_seeds(rs, "ate"), over_seeds(rs, "wall_seconds"), over_seeds(rs, "optimize_seconds"))
            its = sorted({r["iterations"] for r in rs})
            table_rows.append(
                [
                    group,
                    mode,
                    ",".join(map(str, its)),
                    str(len(rs)),
                    pm(stats[mode][0]),
                    pm(stats[mode][1]),
                    pm(stats[mode][2]),
                ]
            )
        scratch_ate, scratch_wall = stats["scratch"][0][0], stats["scratch"][1][0]
        ok_modes = [
            m
            for m in ("frozen", "frozen-short")
            if math.isfinite(stats[m][0][0])
            and stats[m][0][0] <= scratch_ate * (1 + AS_WELL)
            and stats[m][1][0] < scratch_wall
        ]
        holds_groups.append(bool(ok_modes))
        f_ate, f_wall = stats["frozen"][0][0], stats["frozen"][1][0]
        if ok_modes:
            m = ok_modes[0]
            reasons.append(
                f"{group}: {m} {_g(stats[m][0][0])} px in {_g(stats[m][1][0])} s vs scratch {_g(scratch_ate)} px "
                f"in {_g(scratch_wall)} s"
            )
        else:
            reasons.append(
                f"{group}: frozen {_g(f_ate)} px in {_g(f_wall)} s, frozen-short {_g(stats['frozen-short'][0][0])} px "
                f"in {_g(stats['frozen-short'][1][0])} s vs scratch {_g(scratch_ate)} px in {_g(scratch_wall)} s"
            )
    table = _table(["unseen sequences", "mode", "iterations", "runs", "ATE px", "wall s", "optimiser s"], table_rows)
    verdict = "holds" if all(holds_groups) else ("holds partly" if any(holds_groups) else "does not hold")
    reason = "; ".join(reasons)
    short = max(1, round(plan.transfer_iterations * plan.short_fraction))
    body = (
        f"Data: simulated 2D lidar, {plan.transfer_frames} frames a trajectory. Per seed, `strep` is trained on "
        f"{plan.transfer_train} trajectories of map 0 one after the other (each run starts from the previous run's "
        "decoder, occupancy MLP and w, with fresh latents; the saved model of the last one is the trained model), "
        f"then {plan.transfer_test} unseen trajectories of map 0 ('same-map') and {plan.transfer_test} of map 1 "
        "('other-map') are registered three ways: from scratch (the usual per-sequence fit, "
        f"{plan.transfer_iterations} iterations), frozen (`--from-model --freeze`: only fresh latents move, "
        f"{plan.transfer_iterations} iterations, Adam lr `optim.lr_latent_frozen` = 0.1) and frozen-short "
        f"({short} iterations). All start from the ICP warm start. "
        f"{len(train)} training runs. Mean ± std over seeds of the mean over sequences; wall s includes the warm "
        f"start. Frozen counts as 'at least as well' when its ATE is within {AS_WELL:.0%} of scratch's, and as "
        "'in less time' when its mean wall time is lower.\n\n" + table
    )
    return ClaimReport(
        5,
        "A frozen trained model re-optimising only the latents registers unseen sequences as well, faster",
        body,
        verdict,
        reason,
        "claim5_transfer.png",
    )


# --------------------------------------------------------------------------------------------
# Figures


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _legend(ax: Any, **kw: Any) -> None:
    """A legend when the axes have labelled artists, else a note that there is nothing to show."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, **kw)
    else:
        ax.text(0.5, 0.5, "no runs", ha="center", va="center", transform=ax.transAxes)


COLOURS = {"deepmapping": "tab:blue", "strep-nolink": "tab:green", "strep": "tab:red"}


def figure_2d(rows: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, len(SETTINGS), figsize=(13, 4.6), sharey=True, squeeze=False)
    for ax, (setting, (_, text)) in zip(axes[0], SETTINGS.items(), strict=True):
        sel = _ok(rows, claim="2d", setting=setting)
        cases = list(dict.fromkeys(r["case"] for r in sel))
        offsets = {"deepmapping": -0.2, "strep-nolink": 0.0, "strep": 0.2}
        start = per_case_mean(_ok(sel, method="strep"), "initial_ate")
        ax.scatter(
            range(len(cases)),
            [start.get(c, math.nan) for c in cases],
            marker="_",
            s=300,
            c="grey",
            label="start (initial guess)",
        )
        for m in LEARNED:
            rs = _ok(sel, method=m)
            if not rs:
                continue
            xs = [cases.index(r["case"]) + offsets[m] for r in rs]
            ax.scatter(xs, [max(_val(r, "ate"), 1e-3) for r in rs], s=14, c=COLOURS[m], alpha=0.5)
            means = per_case_mean(rs, "ate")
            ax.scatter(
                [cases.index(c) + offsets[m] for c in means],
                list(means.values()),
                s=60,
                marker="D",
                c=COLOURS[m],
                edgecolors="black",
                label=f"{LABEL[m]} (mean; dots: seeds)",
            )
        ax.axhline(FAIL_PX, color="black", ls="--", lw=1, label=f"fails: above {FAIL_PX:g} px")
        ax.axhline(SUCCESS_PX, color="black", ls=":", lw=1, label=f"succeeds: at most {SUCCESS_PX:g} px")
        ax.set_yscale("log")
        ax.set_xticks(range(len(cases)))
        ax.set_xticklabels(cases, rotation=30, ha="right", fontsize=8)
        ax.set_title(f"{setting}: {text}".replace("`", ""), fontsize=9)
        ax.grid(True, which="both", axis="y", alpha=0.3)
    axes[0][0].set_ylabel("ATE (px, log scale)")
    _legend(axes[0][0], loc="center left", framealpha=0.9)
    fig.suptitle("Claims 1-2: ATE per 2D sequence per method")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_3d(rows: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    markers = ["o", "s", "^", "v"]
    for ax, metric, name in zip(axes, ("ate", "point_l2"), ("ATE", "point L2"), strict=True):
        lo, hi = math.inf, 0.0
        for (suite, setting, label), mk in zip(_groups_3d(rows), markers, strict=False):
            sel = _ok(rows, claim="3d", suite=suite, setting=setting)
            dm = per_case_mean(_ok(sel, method="deepmapping"), metric, mm=True)
            st = per_case_mean(_ok(sel, method="strep"), metric, mm=True)
            cs = [c for c in dm if c in st]
            x, y = [dm[c] for c in cs], [st[c] for c in cs]
            ax.scatter(x, y, marker=mk, s=40, label=label, alpha=0.8)
            vals = [v for v in x + y if math.isfinite(v) and v > 0]
            if vals:
                lo, hi = min(lo, *vals), max(hi, *vals)
        if hi > 0:
            ax.plot([lo * 0.8, hi * 1.25], [lo * 0.8, hi * 1.25], color="black", lw=1, ls="--")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"DeepMapping {name} (mm)")
        ax.set_ylabel(f"STREP {name} (mm)")
        ax.set_title(f"{name} per sequence (mean over seeds); below the line: STREP better", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        _legend(ax)
    fig.suptitle("Claim 3: STREP vs DeepMapping on 3D depth")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _curve(
    rows: list[dict[str, Any]], with_start: bool, mm: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mean ATE curve over runs and its std over seeds (of per-seed mean curves), with mean elapsed."""
    per_seed: dict[int, list[np.ndarray]] = {}
    its, times = None, []
    for r in rows:
        h = [p for p in r.get("history") or [] if p[1] is not None]
        if not h:
            continue
        scale = 1000.0 if mm and r.get("unit") == "m" else 1.0
        it = np.array([p[0] for p in h], dtype=float)
        ate = np.array([p[1] for p in h], dtype=float) * scale
        el = np.array([p[2] for p in h], dtype=float)
        if with_start and r.get("initial_ate") is not None:
            it, ate = np.r_[0.0, it], np.r_[r["initial_ate"] * scale, ate]
            el = np.r_[r.get("init_seconds") or 0.0, el]
        if its is None:
            its = it
        if len(it) != len(its):
            continue
        per_seed.setdefault(r["seed"], []).append(ate)
        times.append(el)
    if its is None or not per_seed:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
    seed_means = np.array([np.mean(v, axis=0) for v in per_seed.values()])
    std = seed_means.std(axis=0, ddof=1) if len(seed_means) > 1 else np.zeros(len(its))
    return its, seed_means.mean(axis=0), std, np.mean(times, axis=0)


def figure_ablation(rows: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    groups = _groups_ablation(rows)
    fig, axes = plt.subplots(1, max(1, len(groups)), figsize=(3.4 * max(1, len(groups)), 3.8), squeeze=False)
    for ax, (where, label) in zip(axes[0], groups, strict=False):
        for m in ("strep-nolink", "strep"):
            it, mean, std, _ = _curve(_ok(rows, method=m, **where), with_start=True, mm=True)
            if len(it) == 0:
                continue
            ax.plot(it, mean, color=COLOURS[m], label=LABEL[m])
            ax.fill_between(it, mean - std, mean + std, color=COLOURS[m], alpha=0.2)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("iteration")
        ax.set_ylabel("mean ATE (" + ("mm" if where["claim"] == "3d" else "px") + ")")
        ax.grid(True, alpha=0.3)
        _legend(ax)
    fig.suptitle("Claim 4: ATE versus iteration, linked vs unlinked latents (mean over runs; band: std over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_transfer(rows: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), squeeze=False)
    colours = {"scratch": "tab:blue", "frozen": "tab:red", "frozen-short": "tab:orange"}
    for ax, group in zip(axes[0], ("same-map", "other-map"), strict=True):
        for mode in TRANSFER_MODES:
            it, mean, std, el = _curve(
                _ok(rows, claim="transfer", suite=f"transfer-{group}", setting=mode), with_start=False, mm=False
            )
            if len(it) == 0:
                continue
            ax.plot(el, mean, color=colours[mode], label=mode, marker="." if len(el) < 30 else None)
            ax.fill_between(el, mean - std, mean + std, color=colours[mode], alpha=0.2)
        ax.set_yscale("log")
        ax.set_title(f"unseen trajectories, {group}", fontsize=9)
        ax.set_xlabel("seconds since the run started (incl. the ICP warm start)")
        ax.set_ylabel("mean ATE (px)")
        ax.grid(True, which="both", alpha=0.3)
        _legend(ax)
    fig.suptitle("Claim 5: frozen trained model (latents only) vs optimising from scratch")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# The report


def _fmt_seconds(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"


def build_report(
    rows: list[dict[str, Any]], plan: Plan, meta: dict[str, Any], fig_dir: Path, fig_rel: str
) -> tuple[str, list[ClaimReport]]:
    """The markdown report and its claims; writes the figures into ``fig_dir``."""
    claims = [claim1(rows), claim2(rows), claim3(rows), claim4(rows), claim5(rows, plan)]
    fig_dir.mkdir(parents=True, exist_ok=True)
    figure_2d(rows, fig_dir / "claim1_2d_ate.png")
    figure_3d(rows, fig_dir / "claim3_3d.png")
    figure_ablation(rows, fig_dir / "claim4_ablation.png")
    figure_transfer(rows, fig_dir / "claim5_transfer.png")

    m = meta["machine"]
    failed = [r for r in rows if r.get("status") != "ok"]
    its_2d = sorted({r["iterations"] for r in _ok(rows, claim="2d")})
    its_3d = {s: sorted({r["iterations"] for r in _ok(rows, claim="3d", suite=s)}) for s in ("sevenscenes", "sim3d")}
    lines = [
        "# Reproduction report: do the STREP paper's claims hold here?",
        "",
        f"Written by `strep reproduce{' --quick' if plan.mode == 'quick' else ''}` ({plan.mode} mode) on "
        f"{meta['date']}, code {meta['code'] or 'unknown'}"
        + (f" (cached rows from code {', '.join(meta['row_codes'])})" if meta["row_codes"] != [meta["code"]] else "")
        + ".",
        "",
        f"- Machine: {m['platform']}, {m['cpu_count']} CPU cores, Python {m['python']}, torch {m['torch']}, "
        + (f"GPU {m['cuda']}." if m["cuda"] else "no GPU (every run on the CPU)."),
        f"- Wall time: {_fmt_seconds(meta['runs_seconds'])} for the {len(rows)} runs (sum of their wall times, "
        f"loading included, over every invocation that contributed to the cache); this invocation "
        f"{_fmt_seconds(meta['invocation_seconds'])} ({meta['ran']} runs made, {len(rows) - meta['ran']} from the "
        f"cache). Plan estimate: {_fmt_seconds(meta['estimate']['total'])}.",
        f"- Seeds: 2D {list(plan.seeds_2d)}, 3D {list(plan.seeds_3d)}, claim 5 {list(plan.seeds_transfer)}.",
        f"- Iterations of the learned methods: 2D {its_2d}, 7-Scenes {its_3d['sevenscenes']}, "
        f"sim3d {its_3d['sim3d']}, claim 5 {plan.transfer_iterations} (frozen-short "
        f"{max(1, round(plan.transfer_iterations * plan.short_fraction))}).",
        f"- Failed runs: {len(failed)}"
        + (": " + "; ".join(f"{r['key']} ({r['status']})" for r in failed[:10]) if failed else "."),
        "",
        "## Verdicts",
        "",
        _table(
            ["#", "claim", "verdict", "why"], [[str(c.number), c.title, f"**{c.verdict}**", c.reason] for c in claims]
        ),
        "",
        "## Settings and departures from the paper",
        "",
        "- Every number comes from runs of this implementation (`strep_core.methods.run`), on the benchmark's "
        "cases (`strep_core.bench`) with its per-case configs, changed only in seed, initial guess and (quick "
        "mode) iterations. ATE: RMSE of positions after a rigid alignment; point L2: mean distance of each point "
        "from its true place after aligning the maps (`strep_core.metrics`).",
        "- Two settings for the learned methods: **warm** = "
        + SETTINGS["warm"][1]
        + "; **cold** = "
        + SETTINGS["cold"][1]
        + ". Warm runs predict corrections on top of that start with a truncated point-to-plane Chamfer "
        "loss; cold runs are the paper's setting, with its departures: w starts at 1, the latents learn at "
        "1e-2 (paper 1e-4), Chamfer is Huber over temporal neighbours and, from halfway, truncated over loop "
        "pairs (frames close in the current estimate, far in time; each match weighted window / span) "
        "(`strep_core.config.SCRATCH_PROFILE`, measured in `docs/design/from-scratch.md`).",
        "- The occupancy (global) loss weight is 0 by default in this implementation: with it every measured run "
        "was worse, warm and from scratch (`docs/design/from-scratch.md`). So the occupancy MLP is not trained, "
        "and in claim 5 'frozen' freezes an untrained occupancy MLP along with the trained decoder and w.",
        f"- Claims 1-2 thresholds on 2D sequences in map pixels (the paper's units, maps of 1024 px): a run "
        f"**fails** above {FAIL_PX:g} px (the paper: the baseline's failures average 'more than 100') and "
        f"**succeeds** at or below {SUCCESS_PX:g} px (twice the paper's 'around 10'). A trial is one sequence with "
        "one seed; DeepMapping and STREP trials are paired by seed.",
        f"- Claims 3-4: A beats B when its value is lower by more than {TIE:.0%}; a claim holds when every "
        "comparison is won, does not hold when fewer than half are, and holds partly otherwise.",
        "- Claim 3 uses 7-Scenes windows (real Kinect depth) instead of the Active Vision Dataset, and the "
        "benchmark's simulated AVD-like set (walks with 30-degree turns in a seeded room).",
        "- Claim 5: the optimiser fits one sequence at a time, so 'trained on some sequences' is a chain of "
        "per-sequence fits that hand on the networks (the paper optimises over a set jointly). The frozen "
        "latents' learning rate is `optim.lr_latent_frozen` = 0.1, not the paper's 1e-4 (with 1e-4 the latents "
        "barely move in a few hundred steps).",
        "",
    ]
    for c in claims:
        lines += [f"## Claim {c.number}: {c.title}", "", c.body, ""]
        if c.figure:
            lines += [f"![claim {c.number}]({fig_rel}/{c.figure})", ""]
        lines += [f"**Verdict: {c.verdict}.** {c.reason[:1].upper()}{c.reason[1:]}.", ""]
    return "\n".join(lines), claims


_NUM = re.compile(r"^\**-?\d+(\.\d+)?(e[+-]?\d+)?\**( ± -?\d+(\.\d+)?(e[+-]?\d+)?)?( (mm|px))?( \(.*\))?$")


def check_report(text: str, fig_root: Path | None = None) -> list[str]:
    """Problems of a report: every claim section needs a table with numeric cells, a verdict
    and its figures on disk. Returns an empty list for a complete report."""
    problems = []
    sections = re.split(r"^## ", text, flags=re.M)
    for n in range(1, 6):
        sec = next((s for s in sections if s.startswith(f"Claim {n}:")), None)
        if sec is None:
            problems.append(f"claim {n}: no section")
            continue
        cells = [
            c.strip()
            for line in sec.splitlines()
            if line.startswith("|") and not line.startswith("|---")
            for c in line.strip().strip("|").split("|")
        ]
        if not any(_NUM.match(c) and c not in ("0",) for c in cells):
            problems.append(f"claim {n}: no numeric table cell")
        if not re.search(r"\*\*Verdict: (holds|holds partly|does not hold)\.\*\*", sec):
            problems.append(f"claim {n}: no verdict")
        for img in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", sec):
            if fig_root is not None and not (fig_root / img).is_file():
                problems.append(f"claim {n}: figure {img} missing")
    return problems


def reproduce(
    plan: Plan,
    *,
    out: Path,
    docs: Path,
    data: Path | None = None,
    fresh: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Run a plan (resuming from the cache) and write the report; returns the report's JSON."""
    started = time.perf_counter()
    data = data or DEFAULT_DATA
    runs = build_runs(plan, data)
    est = estimate(runs)
    print(
        f"strep reproduce ({plan.mode}): {len(runs)} runs, estimated {_fmt_seconds(est['total'])} on a quiet "
        "2-core CPU (" + ", ".join(f"{k} {_fmt_seconds(v)}" for k, v in est.items() if k != "total") + ")",
        flush=True,
    )
    out.mkdir(parents=True, exist_ok=True)
    cache = RowCache(out / f"rows-{plan.mode}.json", fresh=fresh)
    rows, ran = run_plan(runs, out, cache, progress=progress)
    meta = {
        "date": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "machine": machine_info(),
        "code": _code_version(),
        "mode": plan.mode,
        "plan": {k: (list(v) if isinstance(v, tuple) else v) for k, v in plan.__dict__.items()},
        "thresholds": THRESHOLDS,
        "estimate": est,
        "ran": ran,
        "runs_seconds": float(sum(r.get("run_seconds") or 0.0 for r in rows)),
        "row_codes": sorted({str(r.get("code")) for r in rows}),
        "invocation_seconds": 0.0,
    }
    fig_dir = docs.parent / docs.stem
    meta["invocation_seconds"] = time.perf_counter() - started
    text, claims = build_report(rows, plan, meta, fig_dir, docs.stem)
    docs.parent.mkdir(parents=True, exist_ok=True)
    docs.write_text(text)
    report = {
        **meta,
        "verdicts": {str(c.number): {"claim": c.title, "verdict": c.verdict, "reason": c.reason} for c in claims},
        "rows": rows,
    }
    (fig_dir / "reproduction.json").write_text(
        json.dumps(report, indent=1, allow_nan=False, default=_json_default) + "\n"
    )
    problems = check_report(text, docs.parent)
    bad_rows = [r["key"] for r in rows if r.get("status") == "ok" and not (r.get("run_seconds", 0) > 0)]
    if bad_rows:
        problems.append(f"rows without a wall time: {bad_rows[:3]}")
    report["problems"] = problems
    return report


def main(args: argparse.Namespace) -> int:
    plan = PLANS["quick" if args.quick else "full"]
    out = Path(args.out) / plan.mode
    docs = Path(args.docs) if args.docs else (out / "reproduction.md" if args.quick else Path("docs/reproduction.md"))
    report = reproduce(plan, out=out, docs=docs, data=args.data, fresh=args.fresh, progress=not args.no_progress)
    for n, v in report["verdicts"].items():
        print(f"claim {n}: {v['verdict']} - {v['reason']}")
    print(
        f"wrote {docs}, figures and reproduction.json in {docs.parent / docs.stem}/ "
        f"({report['ran']} runs made, {_fmt_seconds(report['invocation_seconds'])})"
    )
    if report["problems"]:
        raise ReproduceError("the report is incomplete: " + "; ".join(report["problems"]))
    return 0
