"""The report's PNG figures, one per claim that has one (matplotlib: the ``bench`` extra)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from strep_bench.extras import pyplot
from strep_bench.reproduce.claims import FAIL_PX, LABEL, SUCCESS_PX, groups_3d, groups_ablation
from strep_bench.reproduce.plans import LEARNED, SETTINGS, TRANSFER_MODES
from strep_bench.reproduce.stats import metric_value, ok_rows, per_case_mean


def _legend(ax: Any, **kw: Any) -> None:
    """A legend when the axes have labelled artists, else a note that there is nothing to show."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, **kw)
    else:
        ax.text(0.5, 0.5, "no runs", ha="center", va="center", transform=ax.transAxes)


COLOURS = {"deepmapping": "tab:blue", "strep-nolink": "tab:green", "strep": "tab:red"}


def figure_2d(rows: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, len(SETTINGS), figsize=(13, 4.6), sharey=True, squeeze=False)
    for ax, (setting, (_, text)) in zip(axes[0], SETTINGS.items(), strict=True):
        sel = ok_rows(rows, claim="2d", setting=setting)
        cases = list(dict.fromkeys(r["case"] for r in sel))
        offsets = {"deepmapping": -0.2, "strep-nolink": 0.0, "strep": 0.2}
        start = per_case_mean(ok_rows(sel, method="strep"), "initial_ate")
        ax.scatter(
            range(len(cases)),
            [start.get(c, math.nan) for c in cases],
            marker="_",
            s=300,
            c="grey",
            label="start (initial guess)",
        )
        for m in LEARNED:
            rs = ok_rows(sel, method=m)
            if not rs:
                continue
            xs = [cases.index(r["case"]) + offsets[m] for r in rs]
            ax.scatter(xs, [max(metric_value(r, "ate"), 1e-3) for r in rs], s=14, c=COLOURS[m], alpha=0.5)
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
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    markers = ["o", "s", "^", "v"]
    for ax, metric, name in zip(axes, ("ate", "point_l2"), ("ATE", "point L2"), strict=True):
        lo, hi = math.inf, 0.0
        for (suite, setting, label), mk in zip(groups_3d(rows), markers, strict=False):
            sel = ok_rows(rows, claim="3d", suite=suite, setting=setting)
            dm = per_case_mean(ok_rows(sel, method="deepmapping"), metric, mm=True)
            st = per_case_mean(ok_rows(sel, method="strep"), metric, mm=True)
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
    plt = pyplot()
    groups = groups_ablation(rows)
    fig, axes = plt.subplots(1, max(1, len(groups)), figsize=(3.4 * max(1, len(groups)), 3.8), squeeze=False)
    for ax, (where, label) in zip(axes[0], groups, strict=False):
        for m in ("strep-nolink", "strep"):
            it, mean, std, _ = _curve(ok_rows(rows, method=m, **where), with_start=True, mm=True)
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
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), squeeze=False)
    colours = {"scratch": "tab:blue", "frozen": "tab:red", "frozen-short": "tab:orange"}
    for ax, group in zip(axes[0], ("same-map", "other-map"), strict=True):
        for mode in TRANSFER_MODES:
            it, mean, std, el = _curve(
                ok_rows(rows, claim="transfer", suite=f"transfer-{group}", setting=mode), with_start=False, mm=False
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
