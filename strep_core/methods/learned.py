"""The learned methods: `strep`, its no-link ablation and the DeepMapping baseline.

All three run the same optimiser (`strep_core.optimize.optimize`); only the latent part of the
pose decoder differs (`strep_core.model`). ``init_poses`` is the warm start the runner chose
(the pose graph by default, identity from scratch); the networks predict a correction on top of
it. Decisions and their measurements: docs/design/warm-start.md, docs/design/from-scratch.md.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from strep_core.config import RunConfig
from strep_core.methods.base import MethodOutput, RunContext, method
from strep_core.sequence import Sequence

if TYPE_CHECKING:
    from strep_core.model import Variant

# torch's OpenMP threads wait passively: spinning made an iteration 5x slower on a shared CPU
# (docs/design/warm-start.md, threads). Chosen before torch loads (imported lazily below); a
# value set by the user wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _iterations(seq: Sequence, cfg: RunConfig) -> int:
    from strep_core.batching import total_steps  # (imports torch: after the line above)
    from strep_core.windows import total_iterations, windowed

    return total_iterations(seq, cfg) if windowed(seq, cfg) else total_steps(len(seq), cfg)


def _run(seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext, variant: Variant) -> MethodOutput:
    """One learned run: by windows from scratch past one batch (`strep_core.windows`), else one optimisation."""
    from strep_core.optimize import optimize
    from strep_core.windows import optimize_windows, windowed

    if windowed(seq, config):
        return optimize_windows(seq, init_poses, config, ctx, variant=variant)
    return optimize(seq, init_poses, config, ctx, variant=variant)


@method(
    "strep",
    description="STREP (Wang et al.): temporally linked latents + PointNet pose decoder, Chamfer over frame "
    "neighbourhoods (the occupancy term is off by default: loss.occupancy_weight 0)",
    learned=True,
    total_iterations=_iterations,
)
def strep(seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return _run(seq, init_poses, config, ctx, "strep")


@method(
    "strep-nolink",
    description="STREP ablation: per-frame latents without the temporal link w",
    learned=True,
    total_iterations=_iterations,
)
def strep_nolink(seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return _run(seq, init_poses, config, ctx, "strep-nolink")


@method(
    "deepmapping",
    description="DeepMapping (Ding & Feng 2019): pose from the points alone, no latent",
    learned=True,
    total_iterations=_iterations,
)
def deepmapping(seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return _run(seq, init_poses, config, ctx, "deepmapping")
