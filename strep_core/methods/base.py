"""The method interface: what a registration method is, and the table that names them.

A method is a function ``fn(scene, init_poses, config, ctx) -> MethodOutput`` added to the
table with `@method(name, ...)`. The runner (`strep_core.runner`) wraps every method with the
shared parts (frame selection, initial guess, timing, events, metrics), so all of them return
the same `Result`. This module imports no method: methods import it, the runner imports them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core.config import RunConfig
from strep_core.errors import MethodError
from strep_core.events import CancelFlag, Sink, StageEvent, check_cancel
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
    """What a method function returns; the runner turns it into a `Result`."""

    poses: np.ndarray
    iterations: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)
    artifacts: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    metrics: Mapping[str, float | int] = field(default_factory=dict)  # method-specific, into Result.metrics


MethodFn = Callable[[Sequence, np.ndarray, RunConfig, RunContext], MethodOutput]


@dataclass(frozen=True)
class MethodInfo:
    name: str
    fn: MethodFn
    description: str
    learned: bool
    total_iterations: Callable[[Sequence, RunConfig], int]
    counts: str = "iterations"  # what one of its iterations is, for people ("frames" for incremental methods)


_TABLE: dict[str, MethodInfo] = {}


def method(
    name: str,
    *,
    description: str,
    learned: bool = False,
    total_iterations: Callable[[Sequence, RunConfig], int] | None = None,
    counts: str | None = None,
) -> Callable[[MethodFn], MethodFn]:
    """Decorator adding a method function to the table under ``name`` (a plugin may add its own)."""

    def deco(fn: MethodFn) -> MethodFn:
        _TABLE[name] = MethodInfo(
            name=name,
            fn=fn,
            description=description,
            learned=learned,
            total_iterations=total_iterations or (lambda seq, cfg: len(seq)),
            counts=counts or ("iterations" if learned else "frames"),
        )
        return fn

    return deco


def available() -> dict[str, MethodInfo]:
    """Every method in the table by name, in the order they were added.

    The built-in methods are added when `strep_core.methods` is imported (its ``__init__``
    imports them), which importing this module always does first."""
    return dict(_TABLE)


def get(name: str) -> MethodInfo:
    """The method ``name``; `MethodError` naming the choices when there is none."""
    if name not in _TABLE:
        raise MethodError(f"unknown method {name!r}; choose one of: {', '.join(_TABLE)}")
    return _TABLE[name]
