"""The benchmark's markdown tables: every case, the means per suite, the real 3D pose errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from strep_bench.cases import POSE_ERROR_SUITES
from strep_bench.cases import as_number as _num


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
