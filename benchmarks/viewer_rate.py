"""The viewer's real update rate: pushes per second per job while jobs emit faster than it.

Starts a `ViewerServer` on a free loopback port, feeds ``--jobs`` sinks with iteration events
of a bundled sample at ``--hz`` each for ``--seconds``, and reports per job the events emitted
per second, the pushes per second (aim: at most ``--max-rate``, 10 by default) and the
producer's cost per event in a burst (aim: well under a millisecond: the optimiser is never
held up by the viewer). Unit tests check only the bound per measured window
(`tests/test_viewer.py`, `tests/test_live.py`); this script prints the figures.

Usage::

    python benchmarks/viewer_rate.py [--jobs 2] [--hz 50] [--seconds 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np

from app.core.config import ViewerSettings
from app.viewer import ViewerServer
from strep_core import geometry as g
from strep_core.events import IterationEvent, StartEvent, pose_list
from strep_core.runner import load_input


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--hz", type=float, default=50.0, help="events per second per job")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--max-rate", type=float, default=10.0, help="the viewer's throttle (pushes/s/job)")
    ap.add_argument("--sequence", default="sample:sim2d-small")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()

    seq = load_input(args.sequence)
    gt = g.pose_to_vector(seq.poses)
    rng = np.random.default_rng(0)
    n = max(int(args.hz * args.seconds), 1)
    events = [
        IterationEvent(
            iteration=i,
            total=n,
            elapsed=i / args.hz,
            losses={"total": 1.0 / i},
            ate=1.0 / i,
            poses=pose_list(gt + rng.normal(scale=0.5, size=gt.shape)),
        )
        for i in range(1, n + 1)
    ]
    viewer = ViewerServer(port=0, settings=ViewerSettings(max_rate_hz=args.max_rate))
    rows = []
    try:
        ids = [f"job{j}" for j in range(args.jobs)]
        sinks = [viewer.sink(j, j, seq, group="bench", select=k == 0) for k, j in enumerate(ids)]
        for sink in sinks:
            start = StartEvent(
                method="bench",
                sequence=seq.name,
                frames=len(seq),
                dims=seq.dim,
                unit=seq.unit,
                total_iterations=n,
                initial_guess="identity",
            )
            sink.emit(start)
        viewer.wait_idle(10)
        before = {j: viewer.jobs()[j]["pushes"] for j in ids}
        emitted = dict.fromkeys(ids, 0.0)

        def feed(job: str, sink) -> None:
            t0 = time.perf_counter()
            for k, ev in enumerate(events):
                sink.emit(ev)
                time.sleep(max(t0 + (k + 1) / args.hz - time.perf_counter(), 0.0))
            emitted[job] = time.perf_counter() - t0

        t0 = time.perf_counter()
        threads = [threading.Thread(target=feed, args=(j, s)) for j, s in zip(ids, sinks, strict=True)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        window = time.perf_counter() - t0
        viewer.wait_idle(10)
        jobs = viewer.jobs()
        for j in ids:
            rows.append(
                {
                    "job": j,
                    "events_per_s": n / emitted[j],
                    "pushes_per_s": (jobs[j]["pushes"] - before[j]) / window,
                }
            )
        burst = viewer.sink("burst", "burst", seq, group="bench")
        t = time.perf_counter()
        for ev in events:
            burst.emit(ev)
        emit_us = (time.perf_counter() - t) / len(events) * 1e6
    finally:
        viewer.close()

    print(f"{'job':<8} {'events/s':>9} {'pushes/s':>9}")
    for r in rows:
        print(f"{r['job']:<8} {r['events_per_s']:>9.1f} {r['pushes_per_s']:>9.1f}")
    print(f"producer cost in a burst: {emit_us:.1f} us/event (throttle {args.max_rate:g} pushes/s/job)")
    result = {"jobs": rows, "emit_us_per_event": emit_us, "max_rate_hz": args.max_rate, "window_s": window}
    print(json.dumps(result))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)


if __name__ == "__main__":
    main()
