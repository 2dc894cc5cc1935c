"""Can the reference rank two registrations a millimetre apart? The pair residual says when not.

Where `strep` from the pose graph ends a few per cent above its graph in ATE (freiburg-079[0:100],
freiburg-campus[0:100], lidar_balm), this measures how well each pose set fits the scans
themselves, with no reference: for every pair of scans at most ``--pairs`` apart, 8,192 points of
one (a fixed draw) moved into the other, each point's squared distance to the plane (line in 2D)
of its nearest neighbour among all the other's points, truncated at ``tau``, divided by
``tau^2``, averaged over points and pairs (0: every point on its partner's surface, 1: none within
``tau``). ``tau`` is 0.5, 1 and 2 % of the sequence's scale. Rows: the reference poses, the pose
graph (`multiway`), and `strep` from that graph for each seed. docs/design/warm-start.md.

    PYTHONPATH=. python benchmarks/pair_residual.py --out docs/bench/pair-residual.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

CARMEN = "../shared/data/carmen/{}-corrected.log.gz"
CASES = (
    ("freiburg-079[0:100]", CARMEN.format("freiburg-079"), "0:100"),
    ("freiburg-campus[0:100]", CARMEN.format("freiburg-campus"), "0:100"),
    ("lidar_balm", "../shared/data/lidar_balm", None),
    # controls: windows where strep ends well below its graph in ATE
    ("edmonton[300:400]", CARMEN.format("edmonton"), "300:400"),
    ("acapulco[300:400]", CARMEN.format("acapulco"), "300:400"),
)
FRACTIONS = (0.005, 0.01, 0.02)
QUERIES = 8192


def pair_residual(frames: list[np.ndarray], poses: np.ndarray, tau: float, span: int) -> float:
    """Mean truncated point-to-plane cost (in ``tau^2``) of every scan pair at most ``span`` apart."""
    from scipy.spatial import cKDTree

    from strep_core.losses import frame_normals

    d = frames[0].shape[1]
    rng = np.random.default_rng(0)
    trees = [cKDTree(f) for f in frames]
    normals = [frame_normals(f, k=6 if d == 2 else 20) for f in frames]
    queries = [f[rng.choice(len(f), min(QUERIES, len(f)), replace=False)] for f in frames]
    costs = []
    for a in range(len(frames)):
        for b in range(max(0, a - span), min(len(frames), a + span + 1)):
            if a == b:
                continue
            rel = np.linalg.inv(poses[b]) @ poses[a]
            q = queries[a] @ rel[:d, :d].T + rel[:d, d]
            dist, idx = trees[b].query(q, distance_upper_bound=tau)
            ok = np.isfinite(dist)
            r = np.einsum("ij,ij->i", q[ok] - frames[b][idx[ok]], normals[b][idx[ok]])
            costs.append((np.minimum(r**2, tau**2).sum() + (~ok).sum() * tau**2) / (len(q) * tau**2))
    return float(np.mean(costs))


def case(name: str, source: str, frames: str | None, seeds: list[int], span: int) -> dict[str, object]:
    """The reference, the pose graph and `strep` from that one graph (computed once) per seed."""
    import time

    from strep_core.config import RunConfig
    from strep_core.events import NullSink
    from strep_core.methods import RunContext, get
    from strep_core.metrics import ate
    from strep_core.resolve import resolve
    from strep_core.runner import initial_guess, load_scene

    base = {"frames": frames} if frames else {}
    scene = load_scene(source, RunConfig.build(**base))

    def config(seed: int) -> RunConfig:
        return resolve(RunConfig.build(method="strep", seed=seed), scene).config

    def context() -> RunContext:
        return RunContext(sink=NullSink(), cancel=None, started=time.perf_counter())

    _, graph = initial_guess(scene, config(seeds[0]), context())  # the warm start: the pose graph
    sets = {"reference": scene.poses, "multiway": graph}
    for seed in seeds:
        sets[f"strep seed {seed}"] = get("strep").fn(scene, graph, config(seed), context()).poses
    scale = scene.scale()
    rows = []
    for label, poses in sets.items():
        row: dict[str, object] = {"poses": label, "ate": float(ate(poses, scene.poses))}
        for f in FRACTIONS:
            row[f"residual_{f}"] = pair_residual(scene.frames, poses, f * scale, span)
        rows.append(row)
    return {"case": name, "unit": scene.unit, "scale": scale, "pairs_apart": span, "rows": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--pairs", type=int, default=2, help="scans at most this far apart form a pair")
    ap.add_argument("--cases", nargs="+", default=[c[0] for c in CASES])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    results = [case(n, s, f, args.seeds, args.pairs) for n, s, f in CASES if n in args.cases]
    head = "| case | poses | ATE | " + " | ".join(f"residual at {100 * f:g} % of scale" for f in FRACTIONS) + " |"
    print(head)
    print("|" + "---|" * (3 + len(FRACTIONS)))
    for res in results:
        for row in res["rows"]:  # type: ignore[union-attr]
            cells = " | ".join(f"{row[f'residual_{f}']:.4f}" for f in FRACTIONS)
            print(f"| {res['case']} | {row['poses']} | {row['ate']:.5f} {res['unit']} | {cells} |")
    if args.out:
        args.out.write_text(json.dumps({"rows": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
