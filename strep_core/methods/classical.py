"""Classical baselines: identity, incremental ICP, multiway pose graph, KISS-ICP."""

from __future__ import annotations

import numpy as np

from strep_core.config import RunConfig
from strep_core.methods.registry import MethodOutput, RunContext, register
from strep_core.sequence import Sequence


@register("identity", description="every frame at its initial guess (identity or odometry); a floor")
def identity_method(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return MethodOutput(poses=init.copy())
