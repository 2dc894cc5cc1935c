"""Demo methods that cost no CPU, for developing the web page and testing the service.

Enable them with ``STREP_PLUGINS=app.demo`` (the service and its workers import the module,
which registers the methods). Both emit an `IterationEvent` every ``optim.event_interval``
of ``optim.iterations`` steps of `STEP_SECONDS` each, with a falling fake loss.

* ``demo-sleep`` checks the cancel flag between steps, like every real method;
* ``demo-stubborn`` never does, to exercise the service's terminate-after-grace path.
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
