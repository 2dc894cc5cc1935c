"""Statistics over the rows of a reproduction (means over sequences, then over seeds) and
their text: numbers and markdown tables."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np


def ok_rows(rows: Iterable[dict[str, Any]], **where: Any) -> list[dict[str, Any]]:
    """The finished rows whose fields equal ``where`` (failed runs are left out)."""
    return [r for r in rows if r.get("status") == "ok" and all(r.get(k) == v for k, v in where.items())]


def metric_value(r: dict[str, Any], metric: str, display_mm: bool = False) -> float:
    """A row's metric as a float, NaN when missing or not finite; metres shown in mm if asked."""
    v = r.get(metric)
    if not isinstance(v, (int, float)) or not math.isfinite(v):
        return math.nan
    return float(v) * (1000.0 if display_mm and r.get("unit") == "m" else 1.0)


def mean_std(values: list[float]) -> tuple[float, float, int]:
    """Mean, sample std (0 for one value) and count of the finite values; NaN, NaN, 0 for none."""
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
        per_seed.setdefault(r["seed"], []).append(metric_value(r, metric, mm))
    stats = [
        float(agg([v for v in vals if math.isfinite(v)])) for vals in per_seed.values() if any(map(math.isfinite, vals))
    ]
    return mean_std(stats)


def per_case_mean(rows: list[dict[str, Any]], metric: str, mm: bool = False) -> dict[str, float]:
    """Mean over seeds for every case (in first-seen order)."""
    out: dict[str, list[float]] = {}
    for r in rows:
        out.setdefault(r["case"], []).append(metric_value(r, metric, mm))
    return {c: mean_std(v)[0] for c, v in out.items()}


def fmt_g(v: float) -> str:
    """A number for a table: 3 significant digits, ``-`` for NaN."""
    if not math.isfinite(v):
        return "-"
    return f"{v:.3g}" if abs(v) < 1e5 else f"{v:.3e}"


def pm(stat: tuple[float, float, int]) -> str:
    """``mean ± std`` of a `mean_std` result (the mean alone for one value, ``-`` for none)."""
    m, s, n = stat
    if n == 0:
        return "-"
    return fmt_g(m) if n == 1 else f"{fmt_g(m)} ± {s:.2g}"


def md_table(head: list[str], rows: list[list[str]]) -> str:
    """A markdown table; every row has a cell per column."""
    assert all(len(r) == len(head) for r in rows), (head, [r for r in rows if len(r) != len(head)])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)
