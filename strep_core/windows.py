"""From scratch past one batch: overlapping windows registered alone, joined, then refined together.

The paper registers sequences of up to 256 frames from identity, and so does this project; a
longer sequence optimised as one (batched or not) does not converge from identity (512 frames:
214.6 -> 154.6 px batched, 219.0 px as one batch; docs/design/long-scratch.md). So a learned run
from scratch on more frames than one batch (``optim.batch_frames``, 256 by the resolve stage):

1. **windows**: the sequence is cut into windows of one batch, overlapping by `OVERLAP` frames,
   and each is registered from identity by the paper's model exactly as a sequence of that
   length is (its own decoder, linked latents and temporal chain; `strep_core.optimize`);
2. **join**: each window is moved rigidly onto the frames before it by its shared frames' points
   (each point's two world positions, one rigid fit, `metrics.align_rigid`), then held by a
   trimmed rigid ICP to every frame joined so far (`join_on_map`), so a revisit counts too;
3. **loops** (planar sequences): the windows' chain and its revisits across windows closed as one
   pose graph (`strep_core.window_graph`): a bent window's error no longer rides on through every
   later join;
4. **refine**: one run of the same method over the whole sequence from those poses, in batches,
   with the loop pairs on from the start (`REFINE`): what is left within the Chamfer's reach.

Cost: windows x ``optim.iterations`` + the refinement, linear in frames. The window runs report
as the whole run's progress: their poses joined as far as they go (the live view by
the shared frames alone), the rest where they started.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from strep_core import geometry as g
from strep_core import metrics
from strep_core.batching import batch_schedule, total_steps
from strep_core.config import RunConfig, merge
from strep_core.events import Event, IterationEvent, pose_list
from strep_core.methods.base import MethodOutput, RunContext
from strep_core.sequence import Sequence
from strep_core.window_graph import close_loops, strided, trimmed_icp

if TYPE_CHECKING:
    from strep_core.model import Variant

# Frames each window shares with the one before: half a window, so a join fits one window's middle,
# not two chain ends (1,024 frames joined: 24.9 -> 12.8 px and 37.0 -> 23.6 px against 64;
# docs/design/long-scratch.md).
OVERLAP = 128
# The refinement's settings over the run's own: the joined chain is close, so the loop pairs join
# at once, and fewer iterations than from identity (docs/design/long-scratch.md).
REFINE: dict[str, dict[str, Any]] = {"loss": {"loop_after": 0.0}, "optim": {"iterations": 300}}
# The map join's ICP: iterations, and the share of the window's closest matches it fits.
MAP_ICP_ITERATIONS = 20
MAP_ICP_KEEP = 0.8


def windowed(seq: Sequence, config: RunConfig) -> bool:
    """Whether a learned run of ``config`` on ``seq`` goes by windows: from scratch, longer than a batch."""
    batch = config.optim.batch_frames
    return config.start == "scratch" and isinstance(batch, int) and len(seq) > batch


def windows(num_frames: int, size: int) -> list[np.ndarray]:
    """Contiguous windows of ``size`` frames covering the sequence, each sharing `OVERLAP` with the last."""
    return batch_schedule(num_frames, size, min(OVERLAP, size // 2))


def refine_config(config: RunConfig) -> RunConfig:
    """The refinement's config: the run's own, `REFINE` over it."""
    return RunConfig.build(**merge(config.model_dump(), REFINE))


def total_iterations(seq: Sequence, config: RunConfig) -> int:
    """Steps of a windowed run: every window's, then the refinement's."""
    assert isinstance(config.optim.batch_frames, int)
    wins = windows(len(seq), config.optim.batch_frames)
    return len(wins) * config.optim.iterations + total_steps(len(seq), refine_config(config))


def join(poses: np.ndarray, done: np.ndarray, window: np.ndarray, est: np.ndarray, seq: Sequence) -> np.ndarray:
    """``est`` (the window's poses, its own axes) moved rigidly onto ``poses`` by the frames of
    ``window`` already in ``done``: one rigid fit of the shared frames' points, placed both ways."""
    shared = np.flatnonzero(done[window])
    if len(shared) == 0:
        return est
    pts = [strided(seq.frames[window[i]]) for i in shared]
    src = [g.apply(est[i], p) for i, p in zip(shared, pts, strict=True)]
    dst = [g.apply(poses[window[i]], p) for i, p in zip(shared, pts, strict=True)]
    return g.homogeneous(*metrics.align_rigid(np.concatenate(src), np.concatenate(dst)))[None] @ est


def join_on_map(poses: np.ndarray, done: np.ndarray, window: np.ndarray, est: np.ndarray, seq: Sequence) -> np.ndarray:
    """`join`, then a trimmed rigid ICP of the whole window's points against every frame joined so
    far: a window that revisits an earlier part of the map is held to it, not only to its overlap
    (docs/design/long-scratch.md)."""
    est = join(poses, done, window, est, seq)
    before = np.flatnonzero(done)
    if len(before) == 0:
        return est
    tree = cKDTree(np.concatenate([g.apply(poses[k], strided(seq.frames[k])) for k in before]))
    # the window as one rigid body, in its first frame's axes
    body = np.concatenate([g.apply(g.relative(est[0], est[i]), strided(seq.frames[k])) for i, k in enumerate(window)])
    moved = trimmed_icp(body, tree, est[0], MAP_ICP_ITERATIONS, MAP_ICP_KEEP)
    return (moved @ g.inverse(est[0]))[None] @ est


@dataclass
class _Progress:
    """Re-emits a window run's events as the whole run's: iterations offset, poses joined."""

    ctx: RunContext
    seq: Sequence
    total: int
    poses: np.ndarray  # every frame's latest (joined) poses
    done: np.ndarray  # frames joined so far
    offset: int = 0
    window: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def emit(self, event: Event) -> None:
        if not isinstance(event, IterationEvent) or event.poses is None:
            self.ctx.sink.emit(event)
            return
        est = g.pose_from_vector(np.asarray(event.poses, dtype=np.float64))
        if len(self.window):  # a window's run: its poses joined onto the frames before it
            cur = self.poses.copy()
            cur[self.window] = join(self.poses, self.done, self.window, est, self.seq)
        else:  # the refinement: the whole sequence's
            cur = est
        gt = self.seq.poses
        self.ctx.sink.emit(
            event.model_copy(
                update={
                    "iteration": self.offset + event.iteration,
                    "total": self.total,
                    "poses": pose_list(g.pose_to_vector(cur)),
                    "ate": metrics.ate(cur, gt) if gt is not None else None,
                }
            )
        )


def optimize_windows(
    seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext, *, variant: Variant
) -> MethodOutput:
    """A learned run from scratch over more frames than one batch (see the module docstring)."""
    from strep_core.optimize import optimize

    assert isinstance(config.optim.batch_frames, int)
    wins = windows(len(seq), config.optim.batch_frames)
    rcfg = refine_config(config)
    progress = _Progress(ctx, seq, total_iterations(seq, config), init_poses.copy(), np.zeros(len(seq), bool))
    wctx = RunContext(sink=progress, cancel=ctx.cancel, started=ctx.started)
    history: list[dict[str, Any]] = []
    timings: dict[str, float] = {}
    window_ate: list[float] = []
    ests: list[np.ndarray] = []
    for w in wins:
        progress.window = w
        out = optimize(seq.select(slice(int(w[0]), int(w[-1]) + 1)), init_poses[w], config, wctx, variant=variant)
        ests.append(out.poses)
        progress.poses[w] = join_on_map(progress.poses, progress.done, w, out.poses, seq)
        progress.done[w] = True
        history += [{**h, "iteration": progress.offset + h["iteration"], "ate": None} for h in out.history]
        progress.offset += out.iterations
        for name, value in out.timings.items():
            timings[f"windows_{name}"] = timings.get(f"windows_{name}", 0.0) + value
        if seq.poses is not None:
            window_ate.append(metrics.ate(out.poses, seq.poses[w]))
    joined = progress.poses.copy()
    extra: dict[str, float | int] = {"windows": len(wins)}
    if seq.poses is not None:
        extra.update(joined_ate=metrics.ate(joined, seq.poses), window_ate_max=max(window_ate))
    if seq.dim == 2:
        joined, report = close_loops(seq.frames, wins, ests, joined)
        extra.update(window_loops=report.loops, window_loop_inliers=report.inliers)
        if seq.poses is not None:
            extra["graph_ate"] = metrics.ate(joined, seq.poses)
    # the refinement's events: its own iterations after the windows', its poses the whole sequence's
    progress.window = np.zeros(0, np.int64)
    out = optimize(seq, joined, rcfg, wctx, variant=variant)
    history += [{**h, "iteration": progress.offset + h["iteration"]} for h in out.history]
    timings.update(out.timings)
    return MethodOutput(
        poses=out.poses,
        iterations=progress.offset + out.iterations,
        history=history,
        artifacts=out.artifacts,
        timings=timings,
        metrics=extra,
    )
