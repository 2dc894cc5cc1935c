"""The per-sequence optimisation loop of the learned methods (strep, strep-nolink, deepmapping).

`optimize` fits the networks of `strep_core.model` to one sequence from ``init_poses`` (the pose
graph by default, identity from scratch), minimising with Adam a Chamfer term over frame
neighbourhoods, optionally the occupancy BCE and a weak-direction penalty, over poses
``pose_k = correction_k (x) init_k``. It reports only through ``ctx.sink`` and checks
``ctx.check_cancel()`` before every iteration; the data it works on is packed once by
`strep_core.prepare`, the trained model is saved by `strep_core.artifacts`.

The loop is plan -> step -> report: a `strep_core.plan.BatchPlan` per batch and pair refresh,
a step of tensor operations on the run's device that reads nothing back (the KD-tree search of
`strep_core.neighbours` on a CPU aside), and a report that reads poses and losses on the host
only when it emits an event (docs/design/optimiser.md).

Decisions (the measurements behind each: docs/design/warm-start.md, docs/design/from-scratch.md):

* lengths are divided by `Sequence.scale`: one set of defaults serves pixels and metres;
* the decoder's last layer starts at zero, so iteration 0 (an `IterationEvent`) is exactly the
  starting poses and every chart starts there;
* truncated or Huber Chamfer, point-to-plane by default, threshold annealed: the paper's plain
  squared distances diverge under partial overlap; trimmed (each pair's closest matches) for a
  camera turning in place from scratch, where Huber's minimum lies at half of every turn;
* ``model.planar_axis``: corrections turn about a level camera's vertical axis only (a departure
  from the paper's 6 DoF, on only where the probe finds a turning camera, from scratch);
* occupancy BCE off by default (measured worse); loop pairs from halfway, weighted by the frames
  they span, close the chain from scratch;
* Adam with a cosine schedule; cost per iteration linear in frames and points
  (``benchmarks/iteration_profile.py``);
* long sequences (over 256 frames, whole laser logs) run each step on one batch of 256 frames,
  each batch ``iterations`` times in turn, the batch's spatial partners held at their latest
  poses: peak memory flat in the sequence's length (docs/design/whole-logs.md).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from strep_core import geometry as g
from strep_core import losses, metrics
from strep_core.artifacts import load_into, load_model, model_artifact
from strep_core.batching import batch_schedule, batch_size, total_steps
from strep_core.config import LossConfig, ModelConfig, OptimConfig, RunConfig
from strep_core.device import SectionClock, resolve_device
from strep_core.errors import ConfigError
from strep_core.events import IterationEvent, pose_list
from strep_core.methods.base import MethodOutput, RunContext
from strep_core.model import StrepModel, Variant, compose_correction, correction_pose, planar_vector
from strep_core.pairs import frame_pairs
from strep_core.plan import BatchPlan, build_plan, sample_slots
from strep_core.prepare import Prepared, prepare, weak_matrices
from strep_core.sequence import Sequence


def optimize(
    seq: Sequence,
    init_poses: np.ndarray,
    config: RunConfig,
    ctx: RunContext,
    *,
    variant: Variant,
    profile: bool = False,
) -> MethodOutput:
    """Fit one learned variant to ``seq`` from ``init_poses`` and return its poses.

    Args:
        seq: the sequence (``K`` frames, D = 2 or 3).
        init_poses: ``(K, D+1, D+1)`` warm-start poses (local -> world, sequence unit).
        config: the run config (``model``, ``loss``, ``optim``, ``seed``, ``device``,
            ``threads``, ``from_model``, ``freeze``).
        ctx: sink, cancel flag and clock.
        variant: ``strep``, ``strep-nolink`` or ``deepmapping``.
        profile: on a GPU, wait for the device at every section boundary so the section
            timings are true (slower; `benchmarks/iteration_profile.py`).

    Returns:
        `MethodOutput` with the final poses (one inference pass), the iteration count, the
        loss/ATE history, timings and ``artifacts["model"]`` (see `strep_core.artifacts`).
    """
    threads_before = torch.get_num_threads()
    torch.set_num_threads(config.threads or os.cpu_count() or 1)
    try:
        return _optimize(seq, init_poses, config, ctx, variant, profile)
    finally:
        torch.set_num_threads(threads_before)


# --------------------------------------------------------------------------------------------
# Set-up: everything a run holds fixed


@dataclass
class _Run:
    """One run's fixed parts and its latest poses (``current``, normalised, on the device)."""

    prep: Prepared
    model: StrepModel
    model_cfg: ModelConfig
    optimizer: torch.optim.Optimizer | None
    lc: LossConfig
    oc: OptimConfig
    schedule: list[np.ndarray]
    total: int
    generator: torch.Generator  # the Chamfer term's query samples
    occ_generator: torch.Generator  # the occupancy term's samples: its own stream, so turning it on
    # leaves the Chamfer term's samples as they were
    current: torch.Tensor
    weak: torch.Tensor | None
    base_lrs: list[float] = field(default_factory=list)

    def lr_factor(self, it: int) -> float:
        oc = self.oc
        warm = min(1.0, (it + 1) / oc.warmup_iterations) if oc.warmup_iterations else 1.0
        if oc.schedule == "constant" or self.total <= 1:
            return warm
        f = oc.final_lr_fraction
        return warm * (f + (1.0 - f) * 0.5 * (1.0 + math.cos(math.pi * it / (self.total - 1))))

    def threshold(self, it: int) -> float:
        lc = self.lc
        if lc.threshold_start is None or self.total <= 1:
            return lc.threshold
        return lc.threshold_start * (lc.threshold / lc.threshold_start) ** (it / (self.total - 1))


def _setup(seq: Sequence, init_poses: np.ndarray, config: RunConfig, variant: Variant) -> _Run:
    """Prepared data, the model (loaded and frozen as configured), its Adam optimiser, the schedule."""
    device = torch.device(resolve_device(config.device))
    torch.manual_seed(config.seed)
    oc, lc = config.optim, config.loss
    art = load_model(config.from_model) if config.from_model else None
    model_cfg = config.model if art is None else ModelConfig.model_validate(art["model_config"])
    if art is not None and (art["dim"] != seq.dim or art["variant"] != variant):
        raise ConfigError(
            f"model {config.from_model} is a {art['dim']}D {art['variant']} model; "
            f"this run is a {seq.dim}D {variant} run"
        )
    prep = prepare(seq, init_poses, config, device, np.random.default_rng(config.seed))
    model = StrepModel(variant, prep.dim, prep.num_frames, model_cfg).to(device)
    frozen = art is not None and config.freeze
    if art is not None:
        load_into(model, art)
    lat = model.latents
    networks = [*model.decoder.parameters(), *model.occupancy.parameters()]
    if lat is not None and lat.w is not None:
        networks.append(lat.w)
    groups: list[dict[str, Any]] = []
    if frozen:  # the paper's test-time mode: only the fresh latents move
        for p in networks:
            p.requires_grad_(False)
    else:
        groups.append({"params": networks, "lr": oc.lr_network})
    if lat is not None:
        groups.append({"params": [lat.raw], "lr": oc.lr_latent_frozen if frozen else oc.lr_latent})
    # fused Adam: one kernel over every parameter (CPU 0.6 ms a step against 8 ms per-tensor)
    optimizer = torch.optim.Adam(groups, fused=True) if groups else None
    k = prep.num_frames
    seeds = [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(config.seed).spawn(2)]
    return _Run(
        prep=prep,
        model=model,
        model_cfg=model_cfg,
        optimizer=optimizer,
        lc=lc,
        oc=oc,
        schedule=batch_schedule(k, batch_size(k, oc.batch_frames), lc.window),
        total=total_steps(k, config) if optimizer is not None else 0,
        generator=torch.Generator(device=device).manual_seed(seeds[0]),
        occ_generator=torch.Generator(device=device).manual_seed(seeds[1]),
        current=prep.init.clone(),
        weak=weak_matrices(prep) if lc.weak_weight > 0 else None,
        base_lrs=[grp["lr"] for grp in optimizer.param_groups] if optimizer else [],
    )


# --------------------------------------------------------------------------------------------
# The loop: plan -> step -> report


def _optimize(
    seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext, variant: Variant, profile: bool
) -> MethodOutput:
    clock = SectionClock(torch.device(resolve_device(config.device)), profile=profile)
    t_start = clock.now()
    run = _setup(seq, init_poses, config, variant)
    lc, oc = run.lc, run.oc
    timings = {"setup": clock.now() - t_start}
    history: list[dict[str, Any]] = []
    iteration_times: list[float] = []
    plans: dict[int, BatchPlan] = {}
    pairs_all = np.zeros((0, 2), dtype=np.int64)
    loops_found = False  # spatial pairs computed at least once (they may start late: loop_after)
    if run.total:
        _report(run, seq, ctx, history, 0, {})  # the starting poses: charts start at the start
    clock.lap("events")
    for it in range(run.total):
        ctx.check_cancel()
        t_iter = clock.now()
        loops_on = lc.loop_radius_fraction is not None and it >= lc.loop_after * run.total
        if loops_on and (it % oc.pair_interval == 0 or not loops_found):
            loops_found = True
            pairs_all = _spatial_pairs(run)  # the one host read between events
            plans.clear()
        b = it % len(run.schedule)
        if b not in plans:
            plans[b] = build_plan(
                run.schedule[b],
                pairs_all,
                window=lc.window,
                span_weight=lc.loop_weight == "span",
                device=run.current.device,
            )
        clock.lap("plan")
        loss, terms = _step(run, plans[b], it, clock)
        iteration_times.append(clock.now() - t_iter)
        # one event per event_interval sweeps of the batches: as many events as a one-batch run
        if (it + 1) % (oc.event_interval * len(run.schedule)) == 0 or it + 1 == run.total:
            values = {"total": float(loss.detach()), "chamfer": 0.0, "occupancy": 0.0}
            values.update({n: float(v.detach()) for n, v in terms.items()})
            _report(run, seq, ctx, history, it + 1, values)
            clock.lap("events")
    timings.update(clock.totals)
    if iteration_times:
        timings["iteration_median"] = float(np.median(iteration_times))
    t_final = clock.now()
    final = _final_poses(run)
    timings["final_pass"] = clock.now() - t_final
    timings["optimize"] = clock.now() - t_start
    prep = run.prep
    return MethodOutput(
        poses=_to_world_units(final, prep.scale),
        iterations=run.total,
        history=history,
        artifacts={"model": model_artifact(run.model, run.model_cfg, dim=prep.dim, scale=prep.scale)},
        timings=timings,
    )


def _spatial_pairs(run: _Run) -> np.ndarray:
    """Every spatial (loop) pair at the current poses, sequence indices ``(P0, 2)``."""
    d = run.prep.dim
    lc = run.lc
    return frame_pairs(
        run.prep.num_frames,
        0,
        positions=run.current[:, :d, d].detach().cpu().numpy(),
        radius=lc.loop_radius_fraction,
        max_per_frame=lc.loop_neighbours,
    )


def _report(
    run: _Run, seq: Sequence, ctx: RunContext, history: list[dict[str, Any]], it: int, values: dict[str, float]
) -> None:
    """Read the latest poses on the host and emit them (an `IterationEvent`)."""
    cur = _to_world_units(run.current, run.prep.scale)
    ate = metrics.ate(cur, seq.poses) if seq.poses is not None else None
    elapsed = ctx.elapsed()
    history.append({"iteration": it, "losses": values, "ate": ate, "elapsed": elapsed})
    ctx.sink.emit(
        IterationEvent(
            iteration=it,
            total=run.total,
            elapsed=elapsed,
            losses=values,
            poses=pose_list(g.pose_to_vector(cur)),
            ate=ate,
        )
    )


# --------------------------------------------------------------------------------------------
# One step


def _step(run: _Run, plan: BatchPlan, it: int, clock: SectionClock) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """One Adam step on ``plan``'s frames; returns the loss and its terms (tensors, not read)."""
    assert run.optimizer is not None
    lc = run.lc
    for grp, lr in zip(run.optimizer.param_groups, run.base_lrs, strict=True):
        grp["lr"] = lr * run.lr_factor(it)
    poses, decoded = _batch_poses(run, plan)
    clock.lap("decoder_forward")
    terms: dict[str, torch.Tensor] = {}
    if lc.chamfer_weight > 0:
        terms["chamfer"] = _chamfer(run, plan, poses, run.threshold(it), clock)
        clock.lap("chamfer")
    if lc.weak_weight > 0:
        # translation corrections along directions the frame's normals barely constrain
        assert run.weak is not None
        d = run.prep.dim
        delta = decoded[:, :d, d] - run.prep.init.index_select(0, plan.moving_frames)[:, :d, d]
        weak = run.weak.index_select(0, plan.moving_frames)
        terms["weak"] = torch.einsum("bi,bij,bj->b", delta, weak, delta).mean()
    if lc.occupancy_weight > 0:
        terms["occupancy"] = _occupancy(run, plan, poses, warm=it < lc.occupancy_warmup)
        clock.lap("occupancy_forward")
    weights = {"chamfer": lc.chamfer_weight, "occupancy": lc.occupancy_weight, "weak": lc.weak_weight}
    loss = sum((weights[n] * v for n, v in terms.items()), start=poses.sum() * 0.0)
    run.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    run.optimizer.step()
    run.current.index_copy_(0, plan.frames, poses.detach())
    clock.lap("backward_and_step")
    return loss, terms


def _poses(
    model: StrepModel, prep: Prepared, frames: torch.Tensor, latents: torch.Tensor | None, cfg: ModelConfig
) -> torch.Tensor:
    """``(B, D+1, D+1)`` normalised poses of ``frames`` (decoder + composition)."""
    vec = model(prep.decoder_points.index_select(0, frames), frames, latents)
    if cfg.planar_axis is not None and vec.shape[-1] == 6:
        vec = planar_vector(vec, cfg.planar_axis)
    corr = correction_pose(vec, translation_scale=cfg.translation_scale)
    return compose_correction(prep.init.index_select(0, frames), corr, composition=cfg.composition)


def _batch_poses(run: _Run, plan: BatchPlan) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses of every frame of the step ``(B, D+1, D+1)`` and the decoded (moving) ones.

    The batch's spatial partners outside it join at their latest poses, held fixed: the decoder's
    autograd tape spans the batch only (docs/design/whole-logs.md).
    """
    decoded = _poses(run.model, run.prep, plan.moving_frames, run.model.all_latents(plan.upto), run.model_cfg)
    if not plan.has_fixed:
        return decoded, decoded
    return run.current.index_select(0, plan.frames).index_copy(0, plan.moving, decoded), decoded


def _chamfer(run: _Run, plan: BatchPlan, poses: torch.Tensor, threshold: float, clock: SectionClock) -> torch.Tensor:
    """The Chamfer term of ``plan``'s pairs, each pair's queries moved into its target frame's axes.

    Rigid motions keep distances, so the matches are searched among the target frame's local
    points, which never change (`strep_core.neighbours.FrameIndex`).
    """
    prep, lc = run.prep, run.lc
    d = prep.dim
    width = prep.points.shape[1]
    slot, valid = sample_slots(prep.counts.index_select(0, plan.frames), run.oc.points_per_frame, width, run.generator)
    local = _gather(prep.points, plan.frames.index_select(0, plan.src), slot.index_select(0, plan.src))
    rel = g.inverse(poses.index_select(0, plan.dst)) @ poses.index_select(0, plan.src)
    moved = torch.baddbmm(rel[:, None, :d, d], local, rel[:, :d, :d].transpose(1, 2))
    loop_robust = lc.loop_robust or lc.robust
    # rows whose kernel is truncated need no match beyond the threshold
    near_cut, loop_cut = lc.robust == "truncated", loop_robust == "truncated"
    within = None
    if near_cut or loop_cut:
        within = torch.ones_like(plan.spatial) if near_cut and loop_cut else plan.spatial if loop_cut else ~plan.spatial
    clock.lap("chamfer")
    targets = plan.dst_frames
    found_slot, found = prep.index.nearest(moved.detach(), targets, within=within, limit=threshold)
    found_slot, found = found_slot.to(moved.device), found.to(moved.device)
    clock.lap("nearest_neighbours")
    return losses.pair_chamfer(
        moved,
        _gather(prep.points, targets, found_slot),
        None if prep.normals is None else _gather(prep.normals, targets, found_slot),
        valid.index_select(0, plan.src),
        found,
        plan.spatial,
        plan.weight,
        robust=lc.robust,
        loop_robust=loop_robust,
        threshold=threshold,
        keep=lc.trim_keep,
    )


def _gather(table: torch.Tensor, frames: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
    """``(P, Q, D)`` rows ``slot[p, q]`` of frame ``frames[p]`` of a padded ``(K, N, D)`` table."""
    k, n, d = table.shape
    flat = (frames[:, None] * n + slot).reshape(-1)
    return table.reshape(k * n, d).index_select(0, flat).view(*slot.shape, d)


def _occupancy(run: _Run, plan: BatchPlan, poses: torch.Tensor, *, warm: bool) -> torch.Tensor:
    """Occupancy BCE of sampled points and free-space samples on their rays (world, centred).

    During the warm-up the map learns from the current poses without moving them.
    """
    prep, lc = run.prep, run.lc
    p = poses.detach() if warm else poses
    slot, valid = sample_slots(
        prep.counts.index_select(0, plan.frames), lc.occupancy_points, prep.points.shape[1], run.occ_generator
    )
    hits = g.apply(p, _gather(prep.points, plan.frames, slot))  # (B, S, D)
    sensors = g.apply(p, prep.origins.index_select(0, plan.frames)[:, None, :]).expand_as(hits)
    hits, sensors = hits[valid], sensors[valid]
    free = losses.free_space_samples(sensors, hits, run.occ_generator, per_ray=lc.free_samples)
    logits = run.model.occupancy(torch.cat([hits, free], 0) - prep.centre)
    return losses.occupancy_bce(logits[: len(hits)], logits[len(hits) :])


# --------------------------------------------------------------------------------------------
# The answer


def _final_poses(run: _Run) -> torch.Tensor:
    """One inference pass over every frame, in chunks of a batch."""
    k = run.prep.num_frames
    chunk = batch_size(k, run.oc.batch_frames) or k
    device = run.current.device
    with torch.inference_mode():
        latents = run.model.all_latents()
        return torch.cat(
            [
                _poses(run.model, run.prep, torch.arange(s, min(s + chunk, k), device=device), latents, run.model_cfg)
                for s in range(0, k, chunk)
            ]
        )


def _to_world_units(poses: torch.Tensor, scale: float) -> np.ndarray:
    out = poses.detach().double().cpu().numpy().copy()
    d = out.shape[-1] - 1
    out[:, :d, d] *= scale
    return out
