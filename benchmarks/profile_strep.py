"""Where one STREP iteration's time goes, against its floor (the networks alone).

Runs a few iterations of the real optimiser (`strep_core.optimize.optimize`) on a sequence
and prints its own timers, then times, on the same batch, the floor: the same networks'
forward + backward with a trivial loss (decoder on the decoder points, occupancy MLP on as
many points as the occupancy term feeds it) plus the Adam step.

    .venv/bin/python benchmarks/profile_strep.py                       # v1_pose0, defaults
    .venv/bin/python benchmarks/profile_strep.py --iterations 20 --threads 2 --set optim.points_per_frame=128

Timings on a shared machine are noisy: run it twice and read the lower figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "deepmapping_2d" / "v1_pose0.tar"


def _set(cfg: dict, dotted: str) -> None:
    key, _, value = dotted.partition("=")
    *path, last = key.split(".")
    node = cfg
    for p in path:
        node = node.setdefault(p, {})
    node[last] = json.loads(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="a DeepMapping 2D .tar")
    parser.add_argument("--method", default="strep", choices=["strep", "strep-nolink", "deepmapping"])
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], help="config override, e.g. loss.window=3")
    args = parser.parse_args()

    from strep_core import geometry as g
    from strep_core.batching import batch_size
    from strep_core.config import RunConfig
    from strep_core.events import NullSink
    from strep_core.io.deepmapping import read_deepmapping
    from strep_core.methods.base import RunContext
    from strep_core.model import StrepModel
    from strep_core.optimize import optimize
    from strep_core.prepare import prepare

    seq = read_deepmapping(args.data)
    raw: dict = {"method": args.method, "threads": args.threads, "optim": {"iterations": args.iterations}}
    for s in args.set:
        _set(raw, s)
    cfg = RunConfig.model_validate(raw)
    # A warm start near the answer, as ICP gives: ground truth plus ~1 px / 0.3 degree noise.
    rng = np.random.default_rng(0)
    noise = np.c_[rng.normal(0, 1.0, (len(seq), 2)), rng.normal(0, 0.005, len(seq))]
    assert seq.poses is not None
    init = seq.poses @ g.se2_from_xytheta(noise) if seq.dim == 2 else seq.poses

    t = time.perf_counter()
    out = optimize(seq, init, cfg, RunContext(NullSink(), None, t), variant=args.method)
    n = max(out.iterations, 1)
    tm = out.timings
    sections = [
        "plan",
        "decoder_forward",
        "chamfer",
        "nearest_neighbours",
        "occupancy_forward",
        "backward_and_step",
        "events",
    ]
    loop = sum(tm.get(k, 0.0) for k in sections)
    print(
        f"{args.method} on {seq.name}: {len(seq)} frames, {seq.num_points} points, {n} iterations, "
        f"{cfg.threads or os.cpu_count()} threads"
    )
    print(f"  set-up {1e3 * tm['setup']:.0f} ms, final pass {1e3 * tm['final_pass']:.0f} ms")
    print(f"  one iteration: median {1e3 * tm['iteration_median']:.1f} ms, mean {1e3 * loop / n:.1f} ms, of which")
    for k in sections:
        if k in tm:
            print(f"    {k:<20} {1e3 * tm[k] / n:8.1f} ms  {100 * tm[k] / loop:5.1f} %")

    # Floor: the same networks alone on the same batch (all frames, or one batch), same threads.
    torch.set_num_threads(cfg.threads or os.cpu_count() or 1)
    device = torch.device("cpu")
    prep = prepare(seq, init, cfg, device, np.random.default_rng(0))
    model = StrepModel(args.method, prep.dim, prep.num_frames, cfg.model)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    b = batch_size(prep.num_frames, cfg.optim.batch_frames) or prep.num_frames
    frames = torch.arange(b)
    occ_n = b * min(cfg.loss.occupancy_points, int(prep.counts_host.max())) * (1 + cfg.loss.free_samples)
    occ_x = torch.randn(occ_n, prep.dim)
    times = []
    for _ in range(max(5, min(n, 20))):
        t0 = time.perf_counter()
        z = model.all_latents()
        loss = model(prep.decoder_points[:b], frames, z).sum()
        if cfg.loss.occupancy_weight > 0:
            loss = loss + model.occupancy(occ_x).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t0)
    floor = float(np.median(times[1:]))
    it_ms = tm["iteration_median"]
    print(f"  floor (the same networks' forward + backward + Adam step on the same batch): {1e3 * floor:.1f} ms")
    print(
        f"  iteration / floor = {it_ms / floor:.2f}: everything but the networks is "
        f"{100 * max(it_ms - floor, 0.0) / it_ms:.0f} % of an iteration"
    )


if __name__ == "__main__":
    main()
