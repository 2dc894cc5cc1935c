"""Re-solve saved planar-laser pose graphs under another back end: a trial in seconds a log.

Reads the runs that `benchmarks/laser_headings.py` saved (``DIR/<log>-<deg>/matches.json`` and
``poses.npz``), rebuilds each graph (`graph_from_report`), changes it as the trial says and
optimises it again. ``none`` must give the run's own ATE back (to the JSON's 10 decimals); the
others are round 17's trials (docs/design/laser-slam.md).

    PYTHONPATH=. python benchmarks/graph_trials.py /tmp/headings --trials none across across-robust
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.metrics import ate
from strep_core.registration import laser_graph as lg
from strep_core.registration.laser_slam import graph_from_report
from strep_core.registration.motion_prior import STRAIGHT
from strep_core.registration.submaps import LaserSlamParams

Graph = tuple[np.ndarray, list[lg.Edge], list[lg.StepPrior]]


def _across(robust: bool) -> Callable[[Graph, list[dict[str, Any]]], Graph]:
    """An edge over each run of failed matches: the last scan before it to the first after, at
    the latter's own match covariance. That scan was matched against a submap built mostly before
    the failure, so its pose relative to the last good scan is a measurement, not the bridge's
    guess. ``robust``: among GNC's loop edges, so a wrong one can be let go."""

    def trial(graph: Graph, scans: list[dict[str, Any]]) -> Graph:
        poses, edges, priors = graph
        extra = []
        for k in range(1, len(scans)):
            if scans[k]["verdict"] == "failed" or scans[k - 1]["verdict"] != "failed":
                continue
            i = k - 1
            while i > 0 and scans[i]["verdict"] == "failed":
                i -= 1
            cov = np.asarray(scans[k]["covariance"], dtype=np.float64)
            extra.append(lg.Edge(i, k, g.relative(poses[i], poses[k]), cov, loop=robust))
        return poses, edges + extra, priors

    return trial


def _short_after(graph: Graph, scans: list[dict[str, Any]]) -> Graph:
    """The spacing prior also on an accepted straight step shorter than the spacing that follows
    an ambiguous or failed one (its submap holds the misplaced scan: infinite-corridor 107)."""
    poses, edges, priors = graph
    if not priors:
        return graph
    rel = g.relative(poses[:-1], poses[1:])
    step = np.hypot(rel[:, 0, 2], rel[:, 1, 2])
    turn = np.abs(g.so2_angle(rel[:, :2, :2]))
    spacing, sigma = priors[0].length, priors[0].sigma
    more = [
        lg.StepPrior(k - 1, k, spacing, sigma)
        for k in range(2, len(scans))
        if scans[k]["verdict"] == "accepted"
        and scans[k - 1]["verdict"] != "accepted"
        and turn[k - 1] < STRAIGHT
        and step[k - 1] < spacing
    ]
    return poses, edges, priors + more


def _nearest(graph: Graph, scans: list[dict[str, Any]], *, firm: bool = False) -> Graph:
    """Each closure re-expressed from the submap's scan nearest the matched pose, not from its
    anchor (round 14's closures from the nearest scan, tried again on another draw): the submap's
    own chain between anchor and that scan then stays free instead of being taken as exact.
    ``firm``: only where every step from the anchor to that scan was accepted."""
    poses, edges, priors = graph
    span = next(f.default for f in dataclasses.fields(LaserSlamParams) if f.name == "submap_scans")
    out = []
    for e in edges:
        if not e.loop:
            out.append(e)
            continue
        matched = poses[e.i] @ e.transform
        members = np.arange(e.i, min(e.i + span, len(poses)))
        m = int(members[np.argmin(np.linalg.norm(poses[members, :2, 2] - matched[:2, 2], axis=1))])
        if firm and any(scans[s]["verdict"] != "accepted" for s in range(e.i + 1, m + 1)):
            m = e.i  # a step between anchor and scan slid or failed: the anchor's closure holds it
        out.append(lg.Edge(m, e.j, g.relative(poses[m], matched), e.covariance, e.score, loop=True))
    return poses, out, priors


TRIALS: dict[str, Callable[[Graph, list[dict[str, Any]]], Graph]] = {
    "none": lambda graph, scans: graph,
    "across": _across(robust=False),
    "across-robust": _across(robust=True),
    "short-after": _short_after,
    "nearest": _nearest,
    "nearest-firm": lambda graph, scans: _nearest(graph, scans, firm=True),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, help="a laser_headings.py --out folder")
    ap.add_argument("--trials", nargs="+", default=list(TRIALS), choices=list(TRIALS))
    ap.add_argument("--out", type=Path, help="write the table as JSON here")
    args = ap.parse_args()
    rows = []
    print(f"{'run':<24} " + " ".join(f"{t:>14}" for t in args.trials))
    for run in sorted(p.parent for p in args.runs.glob("*/matches.json")):
        report = json.loads((run / "matches.json").read_text())
        gt = np.load(run / "poses.npz")["gt"]
        row: dict[str, Any] = {"run": run.name}
        for name in args.trials:
            poses, edges, priors = TRIALS[name](graph_from_report(report), report["scans"])
            out, _ = lg.optimise(poses, edges, priors=priors)
            row[name] = round(float(ate(out, gt)), 4)
        rows.append(row)
        print(f"{run.name:<24} " + " ".join(f"{row[t]:>14.4f}" for t in args.trials), flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
