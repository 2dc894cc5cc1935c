"""The planar-laser front and back end of ``multiway``: local SLAM on submaps, loops, GTSAM.

`laser_slam` runs `strep_core.registration.submaps.local_slam` (every scan against a submap,
verdicts and covariances), `strep_core.registration.laser_graph.search_loops` (scans against
finished submaps) and `strep_core.registration.laser_graph.optimise` (graduated
non-convexity over the loops). Every setting is derived from the data (`derive_params`,
`loop_params`); closures that disagree with their neighbours are left out of the graph
(`strep_core.registration.laser_graph.consistent`), and in a keyframed log each ambiguous
straight step shorter than the spacing is held at it softly (`spacing_priors`); why each is what it is:
docs/design/laser-slam.md.

Memory and time are linear in scans: a scan's points, one voxelised cloud per finished
submap, a bounded number of searches per scan, and a sparse graph.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.registration.laser_graph import (
    Edge,
    StepPrior,
    chain_edges,
    consistent,
    loop_params,
    optimise,
    search_loops,
    spacing_priors,
)
from strep_core.registration.submaps import Match, derive_params, local_slam
from strep_core.sequence import Sequence


@dataclass
class LaserSlamResult:
    """Poses ``(K, 3, 3)`` after the graph, the local SLAM's, and what each step decided.

    ``loops``: every closure found; ``left_out``: the ``(i, j)`` of those that disagreed with
    their neighbours and stayed out of the graph; ``loops_kept``: GNC's inliers among the rest;
    ``priors``: the spacing held on short ambiguous steps of a keyframed log (`spacing_priors`);
    ``loop_passes``: the new closures each pass of the loop search found (the last is 0 unless the
    search stopped at `LoopParams.passes`)."""

    poses: np.ndarray
    local_poses: np.ndarray
    matches: list[Match]
    loops: list[Edge]
    loops_kept: int
    loops_tried: int
    left_out: frozenset[tuple[int, int]] = frozenset()
    priors: list[StepPrior] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    loop_passes: tuple[int, ...] = ()

    @property
    def loops_inconsistent(self) -> int:
        return len(self.left_out)

    def verdicts(self) -> dict[str, int]:
        """Count of each verdict over the consecutive matches (scan 0 excluded)."""
        counts = Counter(m.verdict for m in self.matches[1:])
        return {v: counts.get(v, 0) for v in ("accepted", "ambiguous", "failed")}

    def report(self) -> dict[str, Any]:
        """The run's match record, JSON-ready: one entry per scan (its verdict, score, the local
        SLAM's pose ``[x, y, theta]`` and the covariance of its step) and per loop closure (its
        relative pose ``[x, y, theta]`` and covariance), and the spacing priors: the whole pose
        graph, so `graph_from_report` can optimise it again without matching a scan."""
        return {
            "scans": [
                {
                    "verdict": m.verdict,
                    "score": round(float(m.score), 4),
                    "local_pose": _xytheta(pose),
                    "covariance": np.round(m.covariance, 10).tolist(),
                }
                for m, pose in zip(self.matches, self.local_poses, strict=True)
            ],
            "loops": [
                {
                    "from": e.i,
                    "to": e.j,
                    "score": round(float(e.score), 4),
                    "transform": _xytheta(e.transform),
                    "covariance": np.round(e.covariance, 10).tolist(),
                    "consistent": (e.i, e.j) not in self.left_out,
                }
                for e in self.loops
            ],
            "spacing_priors": [
                {"from": p.i, "to": p.j, "length": round(p.length, 10), "sigma": round(p.sigma, 10)}
                for p in self.priors
            ],
            "loops_kept": self.loops_kept,
            "loops_inconsistent": self.loops_inconsistent,
            "loops_tried": self.loops_tried,
            "loop_passes": list(self.loop_passes),
        }


def laser_slam(
    seq: Sequence,
    start: np.ndarray,
    *,
    on_scan: Callable[[int, np.ndarray], None] | None = None,
    on_loop_search: Callable[[int], None] | None = None,
) -> LaserSlamResult:
    """Register a planar laser sequence; scan 0 stays at ``start`` ``(3, 3)``."""
    params = derive_params(seq)
    t0 = time.perf_counter()
    local, matches, submaps = local_slam(seq.frames, params, start=start, on_scan=on_scan)
    t1 = time.perf_counter()
    lp = loop_params(params, seq.scale())
    chain = chain_edges(local, matches)
    priors = spacing_priors(local, matches, params.resolution)
    searched: dict[tuple[int, int], np.ndarray] = {}
    loops, tried = search_loops(
        seq.frames, local, matches, submaps, params, lp, searched=searched, on_scan=on_loop_search
    )
    t2 = time.perf_counter()
    used = consistent(loops, local, matches, params, lp)
    poses, kept = optimise(local, chain + used, priors=priors)
    t_loops, t_graph = t2 - t1, time.perf_counter() - t2
    passes = [len(loops)]
    # searches again from the graph's poses until one finds nothing new (LoopParams.passes): each
    # pass's closures bring into reach revisits that the chain's drift kept out (freiburg-campus
    # 1.21 -> 0.415 m with a second pass, infinite-corridor 1.02 -> 0.365 m with a third and
    # fourth; docs/design/laser-slam.md, round 17)
    for _ in range(lp.passes - 1):
        t2 = time.perf_counter()
        found, n = search_loops(seq.frames, local, matches, submaps, params, lp, estimates=poses, searched=searched)
        have = {(e.i, e.j) for e in loops}
        new = [e for e in found if (e.i, e.j) not in have]
        tried += n
        passes.append(len(new))
        t3 = time.perf_counter()
        t_loops += t3 - t2
        if not new:
            break
        loops += new
        used = consistent(loops, local, matches, params, lp)
        poses, kept = optimise(local, chain + used, priors=priors)
        t_graph += time.perf_counter() - t3
    return LaserSlamResult(
        poses=poses,
        local_poses=local,
        matches=matches,
        loops=loops,
        loops_kept=kept,
        loops_tried=tried,
        left_out=frozenset((e.i, e.j) for e in loops) - {(e.i, e.j) for e in used},
        priors=priors,
        timings={"registration": t1 - t0, "loop_closure": t_loops, "optimization": t_graph},
        loop_passes=tuple(passes),
    )


def _xytheta(pose: np.ndarray) -> list[float]:
    return [round(float(v), 10) for v in g.se2_to_xytheta(pose)]


def graph_from_report(report: dict[str, Any]) -> tuple[np.ndarray, list[Edge], list[StepPrior]]:
    """The pose graph of a run from its `LaserSlamResult.report` (``matches.json``): the local
    SLAM's poses ``(K, 3, 3)``, the edges (the chain, then the consistent closures, in the run's
    order) and the spacing priors. ``optimise(poses, edges, priors=priors)`` gives the run's
    poses again (to the JSON's 10 decimals), so a back end can be compared on a saved run
    in seconds."""
    scans = report["scans"]
    if not scans or any("local_pose" not in s for s in scans) or any("transform" not in e for e in report["loops"]):
        raise ValueError(
            "this matches.json has no local poses or closure transforms: it is not a planar laser's "
            "multiway run, or it was written before they were saved"
        )
    poses = np.stack([g.se2_from_xytheta(np.asarray(s["local_pose"], dtype=np.float64)) for s in scans])
    verdicts = [
        Match(s["verdict"], float(s["score"]), poses[k], np.asarray(s["covariance"])) for k, s in enumerate(scans)
    ]
    edges = chain_edges(poses, verdicts)
    edges += [
        Edge(
            int(e["from"]),
            int(e["to"]),
            g.se2_from_xytheta(np.asarray(e["transform"], dtype=np.float64)),
            np.asarray(e["covariance"], dtype=np.float64),
            float(e["score"]),
            loop=True,
        )
        for e in report["loops"]
        if e["consistent"]
    ]
    priors = [
        StepPrior(int(p["from"]), int(p["to"]), float(p["length"]), float(p["sigma"])) for p in report["spacing_priors"]
    ]
    return poses, edges, priors


def is_planar_laser(seq: Sequence) -> bool:
    """A planar laser recognised from its data: 2D scans whose reader names a laser sensor."""
    sensor = seq.meta.get("sensor")
    return seq.dim == 2 and isinstance(sensor, dict) and sensor.get("kind") == "laser"
