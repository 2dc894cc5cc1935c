"""The per-sequence optimisation loop of the learned methods (strep, strep-nolink, deepmapping).

`optimize` fits the networks of `strep_core.model` to one sequence from ``init_poses`` (the pose
graph by default, identity from scratch), minimising with Adam a Chamfer term over frame
neighbourhoods, optionally the occupancy BCE and a weak-direction penalty, over poses
``pose_k = correction_k (x) init_k``. It reports only through ``ctx.sink`` and checks
``ctx.check_cancel()`` before every iteration; the data it works on is packed by
`strep_core.batching`, the trained model is saved by `strep_core.artifacts`.

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
  (``benchmarks/profile_strep.py``);
* long sequences (over 256 frames, whole laser logs) run each step on one batch of 256 frames,
  each batch ``iterations`` times in turn, the batch's spatial partners held at their latest
  poses: peak memory flat in the sequence's length (docs/design/whole-logs.md).
"""

from __future__ import annotations

import math
import os
import time
from typing import Any

import numpy as np
import torch

from strep_core import geometry as g
from strep_core import losses, metrics
from strep_core.artifacts import load_into, load_model, model_artifact
from strep_core.batching import (
    Prepared,
    batch_schedule,
    batch_size,
    local_pairs,
    prepare,
    ragged_indices,
    sample_per_frame,
    temporal_pairs,
    total_steps,
    weak_matrices,
    with_partners,
)
from strep_core.config import ModelConfig, RunConfig
from strep_core.errors import ConfigError
from strep_core.events import IterationEvent, pose_list
from strep_core.methods.base import MethodOutput, RunContext
from strep_core.model import StrepModel, Variant, compose_correction, correction_pose, planar_vector
from strep_core.sequence import Sequence


def _poses(
    model: StrepModel, prep: Prepared, frames: torch.Tensor, latents: torch.Tensor | None, cfg: ModelConfig
) -> torch.Tensor:
    """``(B, D+1, D+1)`` normalised poses of ``frames`` (decoder + composition)."""
    vec = model(prep.decoder_points.index_select(0, frames), frames, latents)
    if cfg.planar_axis is not None and vec.shape[-1] == 6:
        vec = planar_vector(vec, cfg.planar_axis)
    corr = correction_pose(vec, translation_scale=cfg.translation_scale)
    return compose_correction(prep.init.index_select(0, frames), corr, composition=cfg.composition)


def _transform(poses: torch.Tensor, points: torch.Tensor, owner: torch.Tensor) -> torch.Tensor:
    """World coordinates ``(M, D)`` of local ``points (M, D)``, point m by ``poses[owner[m]]``."""
    d = points.shape[-1]
    b = poses.shape[0]
    if len(points) % b == 0 and bool((owner.view(b, -1) == torch.arange(b, device=owner.device)[:, None]).all()):
        # equal-size frames (the usual case): one batched matrix product
        return torch.baddbmm(poses[:, None, :d, d], points.view(b, -1, d), poses[:, :d, :d].transpose(1, 2)).view(-1, d)
    rot = poses[:, :d, :d].index_select(0, owner)
    trans = poses[:, :d, d].index_select(0, owner)
    return (rot * points[:, None, :]).sum(-1) + trans


# --------------------------------------------------------------------------------------------
# The loop


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device 'cuda' asked for, but torch sees no CUDA device")
    return torch.device(name)


def _to_world_units(poses: torch.Tensor, scale: float) -> np.ndarray:
    out = poses.detach().double().cpu().numpy().copy()
    d = out.shape[-1] - 1
    out[:, :d, d] *= scale
    return out


def optimize(
    seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext, *, variant: Variant
) -> MethodOutput:
    """Fit one learned variant to ``seq`` from ``init_poses`` and return its poses.

    Args:
        seq: the sequence (``K`` frames, D = 2 or 3).
        init_poses: ``(K, D+1, D+1)`` warm-start poses (local -> world, sequence unit).
        config: the run config (``model``, ``loss``, ``optim``, ``seed``, ``device``,
            ``threads``, ``from_model``, ``freeze``).
        ctx: sink, cancel flag and clock.
        variant: ``strep``, ``strep-nolink`` or ``deepmapping``.

    Returns:
        `MethodOutput` with the final poses (one inference pass), the iteration count, the
        loss/ATE history, timings and ``artifacts["model"]`` (see `strep_core.artifacts`).
    """
    threads_before = torch.get_num_threads()
    torch.set_num_threads(config.threads or os.cpu_count() or 1)
    try:
        return _optimize(seq, init_poses, config, ctx, variant)
    finally:
        torch.set_num_threads(threads_before)


class _Clock:
    """Accumulates seconds per named section of the loop (for `MethodOutput.timings`)."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.totals[name] = self.totals.get(name, 0.0) + now - self._last
        self._last = now


def _build(
    seq: Sequence,
    init_poses: np.ndarray,
    config: RunConfig,
    variant: Variant,
    device: torch.device,
    rng: np.random.Generator,
) -> tuple[Prepared, StrepModel, ModelConfig, torch.optim.Optimizer | None]:
    """Prepared data, the model (loaded and frozen as configured) and its Adam optimiser."""
    oc = config.optim
    art = load_model(config.from_model) if config.from_model else None
    model_cfg = config.model if art is None else ModelConfig.model_validate(art["model_config"])
    if art is not None and (art["dim"] != seq.dim or art["variant"] != variant):
        raise ConfigError(
            f"model {config.from_model} is a {art['dim']}D {art['variant']} model; "
            f"this run is a {seq.dim}D {variant} run"
        )
    prep = prepare(seq, init_poses, config, device, rng)
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
    return prep, model, model_cfg, (torch.optim.Adam(groups) if groups else None)


def _optimize(
    seq: Sequence, init_poses: np.ndarray, config: RunConfig, ctx: RunContext, variant: Variant
) -> MethodOutput:
    t_start = time.perf_counter()
    device = _device(config.device)
    torch.manual_seed(config.seed)
    rng, occ_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(config.seed).spawn(2))
    gen = torch.Generator().manual_seed(config.seed)
    lc, oc = config.loss, config.optim
    prep, model, model_cfg, optimizer = _build(seq, init_poses, config, variant, device, rng)
    k, d = prep.num_frames, prep.dim
    batch = batch_size(k, oc.batch_frames)
    schedule = batch_schedule(k, batch, lc.window)
    total = total_steps(k, config) if optimizer is not None else 0

    def lr_factor(it: int) -> float:
        warm = min(1.0, (it + 1) / oc.warmup_iterations) if oc.warmup_iterations else 1.0
        if oc.schedule == "constant" or total <= 1:
            return warm
        f = oc.final_lr_fraction
        return warm * (f + (1.0 - f) * 0.5 * (1.0 + math.cos(math.pi * it / (total - 1))))

    def threshold(it: int) -> float:
        if lc.threshold_start is None or total <= 1:
            return lc.threshold
        return lc.threshold_start * (lc.threshold / lc.threshold_start) ** (it / (total - 1))

    current = prep.init.clone()  # (K, D+1, D+1) latest normalised poses of every frame
    weak = weak_matrices(prep) if lc.weak_weight > 0 else None
    base_lrs = [grp["lr"] for grp in optimizer.param_groups] if optimizer else []
    pairs_all = np.zeros((0, 2), dtype=np.int64)
    pairs_found = False  # spatial pairs computed at least once (they may start late: loop_after)
    history: list[dict[str, Any]] = []
    iteration_times: list[float] = []
    clock = _Clock()
    timings = {"setup": time.perf_counter() - t_start}

    def report(it: int, losses_now: dict[str, float]) -> None:
        cur = _to_world_units(current, prep.scale)
        ate = metrics.ate(cur, seq.poses) if seq.poses is not None else None
        elapsed = ctx.elapsed()
        history.append({"iteration": it, "losses": losses_now, "ate": ate, "elapsed": elapsed})
        ctx.sink.emit(
            IterationEvent(
                iteration=it,
                total=total,
                elapsed=elapsed,
                losses=losses_now,
                poses=pose_list(g.pose_to_vector(cur)),
                ate=ate,
            )
        )

    if total:
        report(0, {})  # the starting poses (no loss evaluated yet): charts start at the start
    it = 0
    while it < total:
        assert optimizer is not None
        ctx.check_cancel()
        t_iter = time.perf_counter()
        clock.lap("events")  # (time since the last lap: the previous event, if any)
        for grp, lr in zip(optimizer.param_groups, base_lrs, strict=True):
            grp["lr"] = lr * lr_factor(it)
        loops_on = lc.loop_radius_fraction is not None and it >= lc.loop_after * total
        if loops_on and (it % oc.pair_interval == 0 or not pairs_found):
            pairs_found = True
            pairs_all = losses.frame_pairs(
                k,
                0,
                positions=current[:, :d, d].detach().cpu().numpy(),
                radius=lc.loop_radius_fraction,
                max_per_frame=lc.loop_neighbours,
            )
        # the batch's spatial partners outside it join at their latest poses, held fixed: the
        # decoder's autograd tape spans the batch only (docs/design/whole-logs.md)
        frames_np, fixed = with_partners(schedule[it % len(schedule)], pairs_all)
        frames_t = torch.as_tensor(frames_np, device=device)
        clock.lap("batching")

        moving_np = frames_np[~fixed]
        moving = torch.as_tensor(moving_np, device=device) if fixed.any() else frames_t
        decoded = _poses(model, prep, moving, model.all_latents(int(moving_np[-1]) + 1), model_cfg)
        if fixed.any():
            poses = current.index_select(0, frames_t)
            poses[torch.as_tensor(~fixed, device=device)] = decoded
        else:
            poses = decoded
        clock.lap("decoder_forward")

        idx, owner = ragged_indices(prep.starts, frames_np)
        idx_t, owner_t = torch.as_tensor(idx, device=device), torch.as_tensor(owner, device=device)
        world = _transform(poses, prep.points.index_select(0, idx_t), owner_t)
        terms: dict[str, torch.Tensor] = {}
        if lc.chamfer_weight > 0:
            normals = None
            if prep.normals is not None:  # rotate the local normals with their frames
                rot_only = torch.cat([poses[:, :d, :d], torch.zeros_like(poses[:, :d, d:])], -1)
                normals = _transform(rot_only, prep.normals.index_select(0, idx_t), owner_t)
            query = sample_per_frame(prep.starts, frames_np, oc.points_per_frame, rng)
            pairs = np.unique(
                np.concatenate([temporal_pairs(frames_np, lc.window), local_pairs(pairs_all, frames_np)]),
                axis=0,
            )
            if fixed.any():  # a pair of two fixed partners moves nothing
                pairs = pairs[~(fixed[pairs[:, 0]] & fixed[pairs[:, 1]])]
            src, target = losses.pair_queries(owner, pairs, query)
            clock.lap("chamfer")
            nn_idx, _ = losses.nearest_in_frame(world.detach().cpu().numpy(), owner, src, target)
            clock.lap("nearest_neighbours")
            # pairs found by proximity (farther apart in time than the window) may use another kernel
            span = np.abs(frames_np[owner[src]] - frames_np[target])
            spatial = span > lc.window
            weight = np.minimum(1.0, lc.window / span) if lc.loop_weight == "span" else None
            kernels = [(~spatial, lc.robust), (spatial, lc.loop_robust or lc.robust)]
            # the frame pair of each match, for the trimmed kernel's per-pair ranking only
            groups = owner[src] * k + target if lc.robust == "trimmed" else None
            terms["chamfer"] = sum(
                (
                    losses.chamfer_matches(
                        world,
                        src[sel],
                        nn_idx[sel],
                        robust=robust,
                        threshold=threshold(it),
                        normals=normals,
                        weights=None if weight is None else weight[sel],
                        groups=None if groups is None else groups[sel],
                        keep=lc.trim_keep,
                    )
                    * (sel.sum() / max(len(src), 1))
                    for sel, robust in kernels
                    if sel.any()
                ),
                start=world.sum() * 0.0,
            )
            clock.lap("chamfer")
        if lc.weak_weight > 0:
            # translation corrections along directions the frame's normals barely constrain
            assert weak is not None
            delta = decoded[:, :d, d] - prep.init.index_select(0, moving)[:, :d, d]
            terms["weak"] = torch.einsum("bi,bij,bj->b", delta, weak.index_select(0, moving), delta).mean()
        if lc.occupancy_weight > 0:
            # during the warm-up the map learns from the current poses without moving them
            warm = it < lc.occupancy_warmup
            occ_idx = torch.as_tensor(
                sample_per_frame(prep.starts, frames_np, lc.occupancy_points, occ_rng), device=device
            )
            hits = (world.detach() if warm else world).index_select(0, occ_idx)
            sensors = _transform(
                poses.detach() if warm else poses,
                prep.origins.index_select(0, frames_t),
                torch.arange(len(frames_np), device=device),
            )
            free = losses.free_space_samples(
                sensors.index_select(0, owner_t.index_select(0, occ_idx)), hits, gen, per_ray=lc.free_samples
            )
            logits = model.occupancy(torch.cat([hits, free], 0) - prep.centre)
            terms["occupancy"] = losses.occupancy_bce(logits[: len(hits)], logits[len(hits) :])
            clock.lap("occupancy_forward")
        loss = sum(
            (
                w * terms[n]
                for n, w in (
                    ("chamfer", lc.chamfer_weight),
                    ("occupancy", lc.occupancy_weight),
                    ("weak", lc.weak_weight),
                )
                if n in terms
            ),
            start=poses.sum() * 0.0,
        )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        clock.lap("backward_and_step")
        current[torch.as_tensor(frames_np)] = poses.detach().to(current.device)
        it += 1
        iteration_times.append(time.perf_counter() - t_iter)

        # one event per event_interval sweeps of the batches: as many events as a one-batch run
        if it % (oc.event_interval * len(schedule)) == 0 or it == total:
            values = {"total": float(loss.detach()), "chamfer": 0.0, "occupancy": 0.0}
            values.update({n: float(v.detach()) for n, v in terms.items()})
            report(it, values)
    clock.lap("events")
    timings.update(clock.totals)
    if iteration_times:
        timings["iteration_median"] = float(np.median(iteration_times))

    t_final = time.perf_counter()
    with torch.inference_mode():
        latents = model.all_latents()
        chunk = batch or k
        final = torch.cat(
            [
                _poses(model, prep, torch.arange(s, min(s + chunk, k), device=device), latents, model_cfg)
                for s in range(0, k, chunk)
            ]
        )
    timings["final_pass"] = time.perf_counter() - t_final
    timings["optimize"] = time.perf_counter() - t_start
    return MethodOutput(
        poses=_to_world_units(final, prep.scale),
        iterations=it,
        history=history,
        artifacts={"model": model_artifact(model, model_cfg, dim=prep.dim, scale=prep.scale)},
        timings=timings,
    )
