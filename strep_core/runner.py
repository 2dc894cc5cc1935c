"""The one place a run is orchestrated: read the input and select its frames once, resolve the
run's settings (`strep_core.resolve`), compute the initial guess, open the sinks, run the method,
measure, write the result files.

`strep run`, the service's worker, ``strep bench`` and ``strep reproduce`` all come through
here (the role KISS-ICP's pipeline plays), so every run of any method gives the same `Result`
and the same files:

* `run_input`: a source (a path or ``sample:NAME``, or a reader the caller supplies) to result
  files, with extra sinks opened once the scene is known (``sinks=lambda scene: [...]``);
* `run`: a `Sequence` already in memory (tests, the benchmark's cases) to a `Result`.

Frame selection (``config.frames``) happens only in `load_scene` and `run`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, cast

import numpy as np

from strep_core import geometry as g
from strep_core import metrics
from strep_core.config import RunConfig
from strep_core.errors import ConfigError
from strep_core.events import CancelFlag, MultiSink, NullSink, ResultEvent, Sink, StageEvent, StartEvent, pose_list
from strep_core.methods import RunContext, get
from strep_core.result import Result, write_outputs
from strep_core.sequence import FrameSelection, Sequence

SceneReader = Callable[[dict[str, Any]], Sequence]
"""Reads a run's input given the reader options (`RunConfig.data`), before the run's frame
selection: the service's worker passes one that applies its upload limits."""

SinkFactory = Callable[[Sequence], Iterable[Sink]]
"""Opens extra sinks once the scene (the selected frames) is known; those that are context
managers are entered, and closed when the method returns or fails."""


def load_input(
    source: str | Path, *, frames: str | FrameSelection | None = None, options: dict[str, Any] | None = None
) -> Sequence:
    """Read ``source``: a path in any supported format, or ``sample:NAME`` for a bundled sample;
    ``options`` go to the reader (`RunConfig.data`)."""
    from strep_core import samples
    from strep_core.io import load_sequence

    text = str(source)
    if samples.is_sample(text):
        return samples.load_sample(text.split(":", 1)[1], frames=frames)
    return load_sequence(text, frames=frames, **(options or {}))


def load_scene(source: str | Path | SceneReader, config: RunConfig) -> Sequence:
    """The frames a run registers: ``source`` read with ``config.data``, ``config.frames`` selected.

    A path is read with the selection (readers skip the frames left out); a `SceneReader`'s
    sequence is selected after reading."""
    options = config.data.options()
    if callable(source):
        seq = source(options)
        return seq.select(config.frames) if config.frames else seq
    return load_input(source, frames=config.frames, options=options)


# --------------------------------------------------------------------------------------------
# The initial guess


def base_guess(seq: Sequence) -> tuple[str, np.ndarray]:
    """The guess every method may start from: the data's odometry if any, else identity."""
    if seq.initial_poses is not None:
        return "odometry", seq.initial_poses.copy()
    return "identity", g.identity(seq.dim, len(seq))


def initial_guess(seq: Sequence, config: RunConfig, ctx: RunContext) -> tuple[str, np.ndarray]:
    """``config.init`` (resolved: `strep_core.resolve`) as a label and ``(K, D+1, D+1)`` poses.

    ``icp``/``multiway``/``kiss`` run that classical method from the base guess (odometry or
    identity) first, its progress reported as ``init:<method>`` stage events (`WarmProgress`);
    ``fpfh`` places views far apart by global feature matching (`strep_core.globalreg`).
    """
    init: str = config.init
    if init == "auto":  # a config that skipped the resolve stage: the base guess
        return base_guess(seq)
    if init == "identity":
        return "identity", g.identity(seq.dim, len(seq))
    if init == "odometry":
        if seq.initial_poses is None:
            raise ConfigError(f"init 'odometry': sequence {seq.name!r} has no odometry")
        return "odometry", seq.initial_poses.copy()
    if init == "ground_truth":
        if seq.poses is None:
            raise ConfigError(f"init 'ground_truth': sequence {seq.name!r} has no ground truth")
        return "ground_truth", seq.poses.copy()
    if init == "fpfh":
        from strep_core import globalreg

        ctx.stage("init:fpfh")
        _, start = base_guess(seq)
        params = globalreg.resolve_global_params(seq, seed=config.seed, threads=config.classical.threads)
        placed = globalreg.fpfh_poses(seq, start, params, on_frame=lambda k: ctx.check_cancel())
        return "fpfh", placed.poses
    # a classical method as warm start, itself from the base guess
    ctx.stage(f"init:{init}")
    label, start = base_guess(seq)
    warm_cfg = config.model_copy(update={"method": init, "init": label})
    progress = WarmProgress(ctx.sink, f"init:{init}")
    out = get(init).fn(seq, start, warm_cfg, RunContext(progress, ctx.cancel, ctx.started))
    return f"{init} (from {label})", out.poses


class WarmProgress:
    """The warm start's sink: its progress as ``init:<method>`` stage events (``done`` of
    ``total`` steps), its other events dropped (they are not the run's own)."""

    def __init__(self, sink: Sink, stage: str) -> None:
        self.sink, self.stage = sink, stage

    def emit(self, event: Any) -> None:
        if event.kind == "iteration" and event.iteration > 0:
            self.sink.emit(StageEvent(stage=self.stage, elapsed=event.elapsed, done=event.iteration, total=event.total))


# --------------------------------------------------------------------------------------------
# Running


def run(
    seq: Sequence,
    config: RunConfig | None = None,
    *,
    sink: Sink | None = None,
    cancel: CancelFlag | None = None,
) -> Result:
    """Run ``config.method`` on the ``config.frames`` of ``seq`` (in memory) and return its `Result`.

    Emits a `StartEvent`, the method's own events and a final `ResultEvent` to ``sink``.
    Raises `Cancelled` if ``cancel`` is set during the run.
    """
    config = config or RunConfig()
    get(config.method)  # an unknown method fails before any work
    if config.frames:
        seq = seq.select(config.frames)
    return run_scene(seq, config, sink=sink, cancel=cancel)


def run_scene(
    scene: Sequence,
    config: RunConfig,
    *,
    sink: Sink | None = None,
    cancel: CancelFlag | None = None,
) -> Result:
    """Run ``config.method`` on ``scene``, whose frames are already selected (`run`, `run_input`)."""
    from strep_core.allocator import keep_freed_memory
    from strep_core.resolve import resolve

    keep_freed_memory()  # numpy's large temporaries reused, not faulted in again (allocator.py)
    sink = sink or NullSink()
    info = get(config.method)
    started = time.perf_counter()
    config = resolve(config, scene).config  # every setting that runs, decided once
    ctx = RunContext(sink=sink, cancel=cancel, started=started)

    label, init_poses = initial_guess(scene, config, ctx)
    t_init = time.perf_counter() - started
    sink.emit(
        StartEvent(
            method=info.name,
            sequence=scene.name,
            frames=len(scene),
            dims=scene.dim,
            unit=scene.unit,
            total_iterations=info.total_iterations(scene, config),
            initial_guess=label,
        )
    )
    ctx.check_cancel()
    out = info.fn(scene, init_poses, config, ctx)
    wall = time.perf_counter() - started

    m: dict[str, Any] = {
        "method": info.name,
        "sequence": scene.name,
        "frames": len(scene),
        "points": scene.num_points,
        "dims": scene.dim,
        "unit": scene.unit,
        "initial_guess": label,
        "profile": config.profile,
        "iterations": out.iterations,
        "iteration_unit": info.counts,  # what they count: optimiser iterations, frames, steps
        "wall_seconds": wall,
        "ate": None,
        "point_l2": None,
        **out.metrics,
    }
    if scene.poses is not None:
        m.update(metrics.evaluate(scene.frames, out.poses, scene.poses))
        m["initial_ate"] = metrics.ate(init_poses, scene.poses)
    result = Result(
        method=info.name,
        sequence=scene,
        poses=out.poses,
        initial_guess=label,
        initial_poses=init_poses,
        metrics=m,
        timings={"initial_guess": t_init, **out.timings, "wall_seconds": wall},
        iterations=out.iterations,
        config=config,
        history=out.history,
        artifacts=out.artifacts,
    )
    sink.emit(
        ResultEvent(
            method=info.name,
            metrics={k: v for k, v in m.items() if isinstance(v, (int, float, str)) or v is None},
            poses=pose_list(g.pose_to_vector(out.poses)),
            iterations=out.iterations,
            wall_seconds=wall,
        )
    )
    return result


def run_input(
    source: str | Path | SceneReader,
    config: RunConfig,
    *,
    out_dir: str | Path | None = None,
    sink: Sink | None = None,
    sinks: SinkFactory | None = None,
    cancel: CancelFlag | None = None,
) -> Result:
    """Read ``source`` once (`load_scene`), run ``config.method`` on it, write the files if asked.

    ``sink`` gets every event, the ``load`` and ``write`` stages included; the sinks
    ``sinks(scene)`` opens (a recording, the worker's scene file) get the run's events, from its
    start to its result. The files written are in ``Result.files``.
    """
    sink = sink or NullSink()
    started = time.perf_counter()
    sink.emit(StageEvent(stage="load", elapsed=0.0))
    scene = load_scene(source, config)
    with contextlib.ExitStack() as stack:
        extra = [_opened(stack, s) for s in (sinks(scene) if sinks else [])]
        result = run_scene(scene, config, sink=MultiSink([sink, *extra]) if extra else sink, cancel=cancel)
    if out_dir is not None:
        sink.emit(StageEvent(stage="write", elapsed=time.perf_counter() - started))
        result.files = write_outputs(result, out_dir)
    return result


def _opened(stack: contextlib.ExitStack[Any], sink: Sink) -> Sink:
    """``sink`` entered on ``stack`` when it is a context manager (closed with the stack), else as is."""
    if isinstance(sink, contextlib.AbstractContextManager):
        return cast(Sink, stack.enter_context(sink))
    return sink
