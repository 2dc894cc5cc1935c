"""Running a plan: each run through `strep_core.runner.run`, its row cached on disk so an
interrupted reproduction resumes where it stopped."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np

from strep_bench.cases import case_config
from strep_bench.reproduce.plans import RunSpec, estimate_run
from strep_core.errors import StrepError
from strep_core.sequence import Sequence


class ReproduceError(StrepError):
    """The report could not be produced or is incomplete."""


def code_version() -> str | None:
    """The repository's short commit (``+dirty`` when strep_core has changes); None without git."""
    root = Path(__file__).resolve().parents[2]  # the repository
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
    from strep_core.artifacts import save_model
    from strep_core.runner import run

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
        tmp.write_text(json.dumps({"rows": list(self.rows.values())}, allow_nan=False, default=json_default))
        os.replace(tmp, self.path)


def json_default(v: Any) -> Any:
    """JSON for numpy scalars (their value) and anything else (its text)."""
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return str(v)


def run_plan(
    runs: list[RunSpec], out: Path, cache: RowCache, *, progress: bool = True
) -> tuple[list[dict[str, Any]], int]:
    """Run (or take from the cache) every spec; returns the rows in plan order and how many ran."""
    from tqdm import tqdm

    code = code_version()

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
