"""Where one iteration of the learned loop goes: milliseconds per section, launches and host syncs.

Runs the real optimiser (`strep_core.optimize.optimize`) from scratch on an input twice per
device: once plain, for the median iteration and its own section timers (on a GPU with
``profile=True``, a sync at each section boundary, so each section is charged its own work), and
once under `torch.profiler`, counting per iteration

* launches: CUDA kernel launches on a GPU; on a CPU, the aten operators called from Python
  (nested ones not counted), the CPU's nearest equivalent;
* syncs: ``cudaStreamSynchronize`` / ``cudaDeviceSynchronize`` / ``cudaEventSynchronize`` /
  blocking ``cudaMemcpy`` calls on a GPU;
* host reads: tensors read on the host (``.numpy()``, ``.item()``, ``.tolist()``, ``float()``,
  ``int()``, ``bool()`` of a tensor), each a sync on a GPU, counted on every device (Adam's step
  counters, host tensors on every device, left out).

It prints a table and writes a JSON (``--json``). Half the iterations run before the loop pairs
join (``loss.loop_after``), half after, as in a from-scratch run. Wall times on a shared machine
are noisy: run it twice and read the lower figures; with ``--threads 1`` the CPU time of an
iteration (``median_cpu_ms``, the process's CPU clock) is the figure least moved by other jobs.

    PYTHONPATH=. python benchmarks/iteration_profile.py                          # sample:sim2d, cpu (+ cuda)
    PYTHONPATH=. python benchmarks/iteration_profile.py --device cuda --iterations 100 --json cuda.json
    PYTHONPATH=. python benchmarks/iteration_profile.py --input sample:sim3d-room --device cpu
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import json
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

_SYNCS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy")
_LAUNCHES = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cudaGraphLaunch")
_READS = ("numpy", "item", "tolist", "__float__", "__int__", "__bool__")


@contextlib.contextmanager
def counting_reads(counts: dict[str, int]) -> Iterator[None]:
    """Count host reads of tensors (see the module docstring) while the block runs."""
    saved = {name: getattr(torch.Tensor, name) for name in _READS}

    def wrap(name: str, fn: Any) -> Any:
        def counted(self: torch.Tensor, *args: Any, **kwargs: Any) -> Any:
            # Adam's step counters live on the host whatever the device: not a read of device memory
            if counts.get("_on") and not sys._getframe(1).f_globals.get("__name__", "").startswith("torch.optim"):
                counts[name] = counts.get(name, 0) + 1
            return fn(self, *args, **kwargs)

        return counted

    for name, fn in saved.items():
        setattr(torch.Tensor, name, wrap(name, fn))
    try:
        yield
    finally:
        for name, fn in saved.items():
            setattr(torch.Tensor, name, fn)


def _config(args: argparse.Namespace, device: str) -> Any:
    from strep_core.config import RunConfig

    raw: dict[str, Any] = {
        "method": args.method,
        "start": "scratch",
        "init": "identity",
        "device": device,
        "threads": args.threads,
        "optim": {"iterations": args.iterations},
    }
    for item in args.set:
        key, _, value = item.partition("=")
        *path, last = key.split(".")
        node = raw
        for p in path:
            node = node.setdefault(p, {})
        node[last] = json.loads(value)
    return RunConfig.model_validate(raw)


def profile_device(args: argparse.Namespace, device: str) -> dict[str, Any]:
    """One device's row: median iteration, sections, launches, syncs and host reads per iteration."""
    from strep_core.events import NullSink
    from strep_core.methods.base import RunContext
    from strep_core.optimize import optimize
    from strep_core.runner import load_scene

    cfg = _config(args, device)
    seq = load_scene(args.input, cfg)
    init = np.broadcast_to(np.eye(seq.dim + 1), (len(seq), seq.dim + 1, seq.dim + 1)).copy()
    extra = {"profile": True} if "profile" in inspect.signature(optimize).parameters else {}

    marks: list[tuple[float, float]] = []

    class _Clocked(RunContext):
        def check_cancel(self) -> None:  # called once before every iteration
            marks.append((time.perf_counter(), time.process_time()))

    t0 = time.perf_counter()
    out = optimize(seq, init, cfg, _Clocked(NullSink(), None, t0), variant=args.method, **extra)
    steps = np.diff(np.array(marks), axis=0)  # wall and CPU seconds from one iteration's start to the next
    n = max(out.iterations, 1)
    sections = {
        k: 1e3 * v / n
        for k, v in out.timings.items()
        if k not in {"setup", "final_pass", "optimize", "iteration_median", "events"}
    }
    row: dict[str, Any] = {
        "device": device,
        "device_name": torch.cuda.get_device_name(0) if device.startswith("cuda") else "cpu",
        "input": args.input,
        "frames": len(seq),
        "iterations": out.iterations,
        "threads": torch.get_num_threads() if args.threads is None else args.threads,
        "median_ms": 1e3 * out.timings["iteration_median"],
        "median_cpu_ms": 1e3 * float(np.median(steps[:, 1])) if len(steps) else None,
        "optimize_s": out.timings["optimize"],
        "sections_ms": sections,
    }

    # the same run under the profiler; counted over the iterations after the first `skip`
    skip = min(args.skip, max(out.iterations - 1, 0))
    active = out.iterations - skip
    counts: dict[str, int] = {}
    seen = {"it": 0}

    class _Ctx(RunContext):
        def check_cancel(self) -> None:  # called once before every iteration
            seen["it"] += 1
            counts["_on"] = int(seen["it"] > skip)
            prof.step()

    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.startswith("cuda"):
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    schedule = torch.profiler.schedule(wait=0, warmup=skip, active=active, repeat=1)
    with counting_reads(counts), torch.profiler.profile(activities=activities, schedule=schedule) as prof:
        optimize(seq, init, cfg, _Ctx(NullSink(), None, time.perf_counter()), variant=args.method)
        counts["_on"] = 0
    events = prof.events() or []
    ops = sum(1 for e in events if e.name.startswith("aten::") and not _under_op(e))
    launches = sum(1 for e in events if e.name in _LAUNCHES)
    syncs = sum(1 for e in events if e.name in _SYNCS)
    per = max(active, 1)
    row.update(
        {
            "profiled_iterations": active,
            "launches_per_iteration": (launches if device.startswith("cuda") else ops) / per,
            "launch_kind": "CUDA kernel launches" if device.startswith("cuda") else "top-level aten ops",
            "syncs_per_iteration": syncs / per if device.startswith("cuda") else None,
            "host_reads_per_iteration": sum(v for k, v in counts.items() if not k.startswith("_")) / per,
            "host_reads": {k: v for k, v in counts.items() if not k.startswith("_")},
        }
    )
    return row


def neighbour_search(args: argparse.Namespace, device: str, repeats: int = 15) -> dict[str, float]:
    """Milliseconds of one step's nearest-neighbour search by each method, at the ground-truth poses.

    The step's shape as late in a from-scratch run: every frame, its temporal pairs and its loop pairs
    (``loss.loop_radius_fraction`` at the true positions), ``optim.points_per_frame`` queries a frame.
    """
    from strep_core import geometry as g
    from strep_core.neighbours import FrameIndex, nearest_in_frame
    from strep_core.optimize import _gather
    from strep_core.pairs import frame_pairs
    from strep_core.plan import build_plan, sample_slots
    from strep_core.prepare import prepare
    from strep_core.runner import load_scene

    cfg = _config(args, device)
    torch.set_num_threads(args.threads or torch.get_num_threads())
    seq = load_scene(args.input, cfg)
    assert seq.poses is not None, "the search is timed at the ground-truth poses"
    dev = torch.device(device)
    prep = prepare(seq, seq.poses, cfg, dev, np.random.default_rng(0))
    d, lc = prep.dim, cfg.loss
    loops = frame_pairs(prep.num_frames, 0, positions=prep.init[:, :d, d].cpu().numpy(), radius=lc.loop_radius_fraction)
    plan = build_plan(np.arange(prep.num_frames), loops, window=lc.window, span_weight=True, device=dev)
    gen = torch.Generator(device=dev).manual_seed(0)
    slot, _ = sample_slots(prep.counts, cfg.optim.points_per_frame, prep.points.shape[1], gen)
    src_frames, dst_frames = plan.frames[plan.src], plan.dst_frames
    poses = prep.init
    rel = g.inverse(poses[dst_frames]) @ poses[src_frames]
    moved = g.apply(rel, _gather(prep.points, src_frames, slot[plan.src]))
    world = g.apply(poses, prep.points)  # (K, N, D): the old search ran over the world points
    n = prep.counts_host
    flat = torch.cat([world[k, : n[k]] for k in range(len(n))]).cpu().numpy()
    frame = np.repeat(np.arange(len(n)), n)
    starts = torch.as_tensor(np.r_[0, np.cumsum(n)[:-1]], device=dev)
    src = (starts[src_frames][:, None] + slot[plan.src]).reshape(-1).cpu().numpy()
    tw = np.repeat(dst_frames.cpu().numpy(), slot.shape[1])

    def timed(fn: Any) -> float:
        fn()
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            ts.append(time.perf_counter() - t)
        return 1e3 * float(np.median(ts))

    out = {"queries": float(moved.shape[0] * moved.shape[1]), "pairs": float(moved.shape[0])}
    brute = FrameIndex(prep.points, prep.counts, backend="brute")
    out["brute force, chunked (ms)"] = timed(lambda: brute.nearest(moved, dst_frames))
    if device == "cpu":
        tree = FrameIndex(prep.points, prep.counts, backend="tree")
        out["KD-tree rebuilt over world points (before, ms)"] = timed(lambda: nearest_in_frame(flat, frame, src, tw))
        out["KD-tree over static local points (ms)"] = timed(lambda: tree.nearest(moved, dst_frames))
        within = plan.spatial if (lc.loop_robust or lc.robust) == "truncated" else None
        thr = lc.threshold_start or lc.threshold
        out["  loop pairs within the threshold (ms)"] = timed(
            lambda: tree.nearest(moved, dst_frames, within=within, limit=thr)
        )
    return out


def _under_op(event: Any) -> bool:
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith("aten::"):
            return True
        parent = parent.cpu_parent
    return False


def table(rows: list[dict[str, Any]]) -> str:
    names = sorted(
        {k for r in rows for k in r["sections_ms"]}, key=lambda k: -max(r["sections_ms"].get(k, 0) for r in rows)
    )
    head = f"| {'':<26} | " + " | ".join(f"{r['device']:>10}" for r in rows) + " |"
    line = "|" + "-" * 28 + "|" + "|".join("-" * 12 for _ in rows) + "|"

    def row(label: str, values: list[str]) -> str:
        return f"| {label:<26} | " + " | ".join(f"{v:>10}" for v in values) + " |"

    out = [head, line, row("median iteration (ms)", [f"{r['median_ms']:.1f}" for r in rows])]
    out.append(row("  its CPU time (ms)", [f"{r['median_cpu_ms']:.1f}" for r in rows]))
    out += [row(f"  {k} (ms)", [f"{r['sections_ms'].get(k, 0.0):.1f}" for r in rows]) for k in names]
    out.append(row("launches / iteration", [f"{r['launches_per_iteration']:.0f}" for r in rows]))
    out.append(
        row(
            "syncs / iteration",
            ["-" if r["syncs_per_iteration"] is None else f"{r['syncs_per_iteration']:.1f}" for r in rows],
        )
    )
    out.append(row("host reads / iteration", [f"{r['host_reads_per_iteration']:.1f}" for r in rows]))
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", default="sample:sim2d", help="a file, folder or sample:NAME")
    parser.add_argument("--method", default="strep", choices=["strep", "strep-nolink", "deepmapping"])
    parser.add_argument("--device", nargs="+", default=None, help="cpu, cuda (default: cpu, and cuda if present)")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--skip", type=int, default=5, help="first iterations left out of the profiler's counts")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], help="config override, e.g. loss.window=3")
    parser.add_argument("--json", type=Path, default=None, help="write the rows here")
    parser.add_argument("--neighbours", action="store_true", help="time only the nearest-neighbour search methods")
    args = parser.parse_args()
    devices = args.device or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    if args.neighbours:
        found = {d: neighbour_search(args, d) for d in devices}
        for d, row in found.items():
            print(f"{args.input} on {d}: " + ", ".join(f"{k} {v:.1f}" for k, v in row.items()))
        if args.json:
            args.json.write_text(json.dumps(found, indent=2) + "\n")
        return
    rows = [profile_device(args, d) for d in devices]
    print(f"{args.method} from scratch on {args.input}: {rows[0]['frames']} frames, {args.iterations} iterations")
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
