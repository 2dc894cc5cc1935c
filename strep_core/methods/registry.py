"""One registry for every registration method, classical and learned.

A method is a function ``fn(seq, init_poses, config, ctx) -> MethodOutput``; `run` wraps it
with the shared parts: frame selection, the initial guess, timing, events and metrics, so
every method returns the same `Result` and any two runs compare side by side.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core import metrics
from strep_core.config import RunConfig
from strep_core.errors import ConfigError, MethodError
from strep_core.events import (
    CancelFlag,
    NullSink,
    ResultEvent,
    Sink,
    StageEvent,
    StartEvent,
    check_cancel,
    pose_list,
)
from strep_core.result import Result
from strep_core.sequence import Sequence


@dataclass
class RunContext:
    """What a method may use besides its input: the sink, the cancel flag and the clock."""

    sink: Sink
    cancel: CancelFlag | None
    started: float

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def check_cancel(self) -> None:
        check_cancel(self.cancel)

    def stage(self, name: str) -> None:
        self.sink.emit(StageEvent(stage=name, elapsed=self.elapsed()))


@dataclass
class MethodOutput:
    """What a method function returns; `run` turns it into a `Result`."""

    poses: np.ndarray
    iterations: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)
    artifacts: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, float | int] = field(default_factory=dict)  # method-specific, into Result.metrics


MethodFn = Callable[[Sequence, np.ndarray, RunConfig, RunContext], MethodOutput]


@dataclass(frozen=True)
class MethodInfo:
    name: str
    fn: MethodFn
    description: str
    learned: bool
    total_iterations: Callable[[Sequence, RunConfig], int]


_REGISTRY: dict[str, MethodInfo] = {}


def register(
    name: str,
    *,
    description: str,
    learned: bool = False,
    total_iterations: Callable[[Sequence, RunConfig], int] | None = None,
) -> Callable[[MethodFn], MethodFn]:
    """Decorator adding a method function to the registry under ``name``."""

    def deco(fn: MethodFn) -> MethodFn:
        _REGISTRY[name] = MethodInfo(
            name=name,
            fn=fn,
            description=description,
            learned=learned,
            total_iterations=total_iterations or (lambda seq, cfg: len(seq)),
        )
        return fn

    return deco


def _load_builtin() -> None:
    # Importing the modules registers their methods; heavy imports stay inside functions.
    import importlib.util

    from strep_core.methods import classical  # noqa: F401

    if importlib.util.find_spec("strep_core.methods.learned") is not None:  # TEMP until it lands
        from strep_core.methods import learned  # noqa: F401


def available() -> dict[str, MethodInfo]:
    """All registered methods by name, in registration order."""
    _load_builtin()
    return dict(_REGISTRY)


def get(name: str) -> MethodInfo:
    methods = available()
    if name not in methods:
        raise MethodError(f"unknown method {name!r}; choose one of: {', '.join(methods)}")
    return methods[name]


def base_guess(seq: Sequence) -> tuple[str, np.ndarray]:
    """The guess every method may start from: the data's odometry if any, else identity."""
    if seq.initial_poses is not None:
        return "odometry", seq.initial_poses.copy()
    return "identity", g.identity(seq.dim, len(seq))


# The learned methods' default warm start. The pose graph refines incremental ICP with loop
# closures; the networks then refine it. Measured (strep, 60 iterations, three 96-frame sim2d
# trajectories): from multiway 0.151 / 0.478 / 0.436 px (mean 0.355); from icp in the previous
# quick benchmark 1.25 / 0.268 / 0.826 px (mean 0.782).
LEARNED_WARM_START = "multiway"


def initial_guess(seq: Sequence, config: RunConfig, ctx: RunContext, *, learned: bool) -> tuple[str, np.ndarray]:
    """Resolve ``config.init`` into a label and ``(K, D+1, D+1)`` starting poses.

    ``auto`` is the base guess (odometry or identity) for classical methods, and a pose-graph
    (``multiway``: incremental ICP plus loop closures) warm start from that base guess for
    learned ones. ``icp``/``multiway``/``kiss`` run that
    classical method from the base guess first.
    """
    init = config.init
    if init == "auto":
        init = LEARNED_WARM_START if learned else "base"
    if init == "base":
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
        # global alignment (FPFH + RANSAC, refined by ICP) for views far apart, from the base guess
        from strep_core import globalreg

        ctx.stage("init:fpfh")
        _, start = base_guess(seq)
        params = globalreg.resolve_global_params(seq, seed=config.seed, threads=config.classical.threads)
        placed = globalreg.fpfh_poses(seq, start, params, on_frame=lambda k: ctx.check_cancel())
        return "fpfh", placed.poses
    # a classical method as warm start, itself from the base guess
    ctx.stage(f"init:{init}")
    label, start = base_guess(seq)
    warm_cfg = config.model_copy(update={"method": init, "init": "auto"})
    out = get(init).fn(seq, start, warm_cfg, RunContext(NullSink(), ctx.cancel, ctx.started))
    return f"{init} (from {label})", out.poses


def run(
    seq: Sequence,
    config: RunConfig | None = None,
    *,
    sink: Sink | None = None,
    cancel: CancelFlag | None = None,
) -> Result:
    """Run ``config.method`` on ``seq`` and return its `Result` with metrics.

    Emits a `StartEvent`, the method's own events, and a final `ResultEvent` to ``sink``.
    Raises `Cancelled` if ``cancel`` is set during the run.
    """
    config = config or RunConfig()
    sink = sink or NullSink()
    info = get(config.method)
    if config.frames:
        seq = seq.select(config.frames)
    started = time.perf_counter()
    from strep_core.profiles import resolve

    config = resolve(config, seq)  # settings chosen from the data (or the profile named)
    ctx = RunContext(sink=sink, cancel=cancel, started=started)

    label, init_poses = initial_guess(seq, config, ctx, learned=info.learned)
    t_init = time.perf_counter() - started
    sink.emit(
        StartEvent(
            method=info.name,
            sequence=seq.name,
            frames=len(seq),
            dims=seq.dim,
            unit=seq.unit,
            total_iterations=info.total_iterations(seq, config),
            initial_guess=label,
        )
    )
    ctx.check_cancel()
    out = info.fn(seq, init_poses, config, ctx)
    wall = time.perf_counter() - started

    m: dict[str, Any] = {
        "method": info.name,
        "sequence": seq.name,
        "frames": len(seq),
        "points": seq.num_points,
        "dims": seq.dim,
        "unit": seq.unit,
        "initial_guess": label,
        "profile": config.profile,
        "iterations": out.iterations,
        "wall_seconds": wall,
        "ate": None,
        "point_l2": None,
        **out.metrics,
    }
    if seq.poses is not None:
        m.update(metrics.evaluate(seq.frames, out.poses, seq.poses))
        m["initial_ate"] = metrics.ate(init_poses, seq.poses)
    timings = {"initial_guess": t_init, **out.timings, "wall_seconds": wall}
    result = Result(
        method=info.name,
        sequence=seq,
        poses=out.poses,
        initial_guess=label,
        initial_poses=init_poses,
        metrics=m,
        timings=timings,
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
