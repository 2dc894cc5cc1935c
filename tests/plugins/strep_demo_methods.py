"""Demo methods for the service's tests (not shipped: they live under ``tests/plugins``).

Enable them with ``STREP_PLUGINS=strep_demo_methods`` and ``tests/plugins`` on the Python path
(``tests/conftest.py`` does both for the tests' processes). The sleeping ones emit an
`IterationEvent` every ``optim.event_interval`` of ``optim.iterations`` steps of `STEP_SECONDS`
each, with a falling fake loss.

* ``demo-sleep`` checks the cancel flag between steps, like every real method;
* ``demo-stubborn`` never does, to exercise the service's terminate-after-grace path;
* ``demo-hog`` allocates `HOG_STEP_MIB` every step up to `HOG_LIMIT_MIB`, to exercise the
  per-job memory budget (``STREP_JOB_MEMORY_MIB``).
"""

from __future__ import annotations

import time

import numpy as np

from strep_core import geometry as g
from strep_core.config import RunConfig
from strep_core.events import IterationEvent, pose_list
from strep_core.methods.base import MethodOutput, RunContext, method
from strep_core.sequence import Sequence

STEP_SECONDS = 0.02
HOG_STEP_MIB = 32
HOG_LIMIT_MIB = 2048  # a bound of its own, should the budget not stop it


def _steps(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext, *, check_cancel: bool) -> MethodOutput:
    total = config.optim.iterations
    interval = config.optim.event_interval
    poses = init.copy()
    for i in range(1, total + 1):
        if check_cancel:
            ctx.check_cancel()
        time.sleep(STEP_SECONDS)
        if i % interval == 0 or i == total:
            ctx.sink.emit(
                IterationEvent(
                    iteration=i,
                    total=total,
                    elapsed=ctx.elapsed(),
                    losses={"total": 1.0 / i},
                    poses=pose_list(g.pose_to_vector(poses)),
                    ate=None,
                )
            )
    return MethodOutput(poses=poses, iterations=total)


def _total(seq: Sequence, config: RunConfig) -> int:
    return config.optim.iterations


@method("demo-sleep", description="demo: sleeps optim.iterations steps, emitting events", total_iterations=_total)
def demo_sleep(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return _steps(seq, init, config, ctx, check_cancel=True)


@method("demo-stubborn", description="demo: like demo-sleep but ignores cancellation", total_iterations=_total)
def demo_stubborn(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return _steps(seq, init, config, ctx, check_cancel=False)


@method("demo-hog", description="demo: allocates memory until the job's budget stops it", total_iterations=_total)
def demo_hog(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    held = []
    for _ in range(HOG_LIMIT_MIB // HOG_STEP_MIB):
        ctx.check_cancel()
        held.append(np.ones(HOG_STEP_MIB * 2**20 // 8))  # written: resident, not only reserved
        time.sleep(STEP_SECONDS)
    return MethodOutput(poses=init.copy(), iterations=len(held))
