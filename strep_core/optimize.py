"""The per-sequence optimisation loop of the learned methods (strep, strep-nolink, deepmapping).

`optimize` fits the networks of `strep_core.model` to one sequence from ``init_poses``
(``start="pose-graph"``: by default the ``multiway`` pose graph, i.e. incremental ICP plus loop
closures; ``start="scratch"``: identity, the paper's setting), minimising with Adam

    L = chamfer_weight * Chamfer(frames, neighbours) + occupancy_weight * occupancy BCE
        + weak_weight * mean_k  dt_k^T A_k dt_k   (translation corrections along weak directions)

over poses ``pose_k = correction_k (x) init_k`` decoded by the networks. It reports only
through ``ctx.sink`` (an `IterationEvent` every ``optim.event_interval`` iterations, with the
current poses of every frame and the ATE when ground truth exists), calls
``ctx.check_cancel()`` before every iteration, and ends with one inference pass that gives
the final poses. `save_model` / `load_model` write and read the trained networks; with
``config.from_model`` and ``config.freeze`` only fresh latents are optimised (test-time mode).

Decisions (measurement histories: docs/design/warm-start.md for the pose-graph start,
docs/design/from-scratch.md for the start from identity):

* Units: local points and translations are divided by `Sequence.scale`, so one set of
  defaults serves pixels and metres.
* The decoder's last layer is zero-initialised: iteration 0 is exactly the starting poses,
  reported as an `IterationEvent` with ``iteration=0`` so that every chart starts there.
* Chamfer over neighbourhoods: temporal neighbours within ``+-window`` frames, plus spatial
  neighbours (sensors within ``loop_radius * scale``, recomputed every ``pair_interval``
  iterations, from ``loop_after * iterations`` on); truncated or Huber distances, point-to-plane
  by default, the threshold annealed from ``threshold_start`` to ``threshold``. The paper's
  plain squared distances diverge under partial overlap (a departure, docs/reproduction.md).
* ``weak_weight``: a penalty on each frame's translation correction along the directions its own
  normals constrain weakly (a corridor's axis), which the Chamfer terms cannot see; off by
  default, on in the ``laser-keyframes`` profile (docs/design/warm-start.md, weak directions).
* Occupancy BCE (the paper's global term) is weighted by ``occupancy_weight``; off by
  default in both starts, because measured it made every run worse (see the two designs).
* From scratch (`SCRATCH_PROFILE`): ``w`` starts at 1 (the linked latents then form an
  integrator of per-frame increments), the latents learn at 1e-2 (the paper: 1e-4), Huber
  distances between temporal pairs; from halfway, loop pairs close the chain with truncated
  distances, each match weighted ``window / span``: a loop spanning n frames moves n
  increments of the chain, and unweighted (Adam gives every increment a full step) it tore
  v1_pose0 apart (2 px -> 106 px).
* Adam, a cosine schedule down to ``final_lr_fraction``; a fixed strided subset of
  ``decoder_points`` points per frame feeds the decoder; ``points_per_frame`` random queries
  per frame and step.

Cost per iteration is linear in frames and points: one decoder pass over ``K x
decoder_points`` points, one KD-tree over the batch's points, ``K x points_per_frame x
(pairs per frame)`` queries. See ``benchmarks/profile_strep.py``.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from strep_core import geometry as g
from strep_core import losses, metrics
from strep_core.config import ModelConfig, RunConfig
from strep_core.errors import ConfigError
from strep_core.events import IterationEvent, pose_list
from strep_core.methods.registry import MethodOutput, RunContext
from strep_core.model import (
    Latents,
    OccupancyMLP,
    PoseDecoder,
    Variant,
    compose_correction,
    correction_pose,
)
from strep_core.sequence import Sequence

ARTIFACT_VERSION = 1


# --------------------------------------------------------------------------------------------
# Data prepared once per run


@dataclass
class Prepared:
    """A sequence as float32 tensors in normalised units.

    Attributes:
        dim: D.
        scale: the sequence's `scale` (length unit per normalised unit).
        points: ``(M, D)`` local points of every frame (working set), concatenated.
        starts: ``(K + 1,)`` int64: frame ``k`` owns ``points[starts[k]:starts[k+1]]``.
        decoder_points: ``(K, Nd, D)`` the fixed decoder input of every frame.
        origins: ``(K, D)`` sensor origins, local.
        init: ``(K, D+1, D+1)`` warm-start poses, translations normalised.
        centre: ``(D,)`` normalised world centre of the warm-start trajectory (occupancy input
            is ``world - centre``).
        normals: ``(M, D)`` local unit normals of ``points`` (``loss.chamfer="plane"``), else None.
    """

    dim: int
    scale: float
    points: torch.Tensor
    starts: np.ndarray
    decoder_points: torch.Tensor
    origins: torch.Tensor
    init: torch.Tensor
    centre: torch.Tensor
    normals: torch.Tensor | None = None

    @property
    def num_frames(self) -> int:
        return len(self.starts) - 1


def _strided(n: int, m: int | None) -> np.ndarray:
    """``min(n, m)`` evenly spread indices of ``range(n)``; ``m`` of them (repeating) if n < m."""
    if m is None or n == m:
        return np.arange(n)
    return np.floor(np.arange(m) * (n / m)).astype(np.int64)


def prepare(
    seq: Sequence, init_poses: np.ndarray, config: RunConfig, device: torch.device, rng: np.random.Generator
) -> Prepared:
    """Normalise and pack a sequence for the optimiser (see `Prepared`)."""
    scale = seq.scale()
    cap = config.optim.max_points_per_frame
    frames = []
    for f in seq.frames:
        if len(f) > cap:
            f = f[np.sort(rng.choice(len(f), cap, replace=False))]
        frames.append(f / scale)
    counts = np.array([len(f) for f in frames])
    nd = config.model.decoder_points
    nd = int(counts.max()) if nd is None else min(nd, int(counts.max()))
    dec = np.stack([f[_strided(len(f), nd)] for f in frames])
    init = np.array(init_poses, dtype=np.float64, copy=True)
    d = seq.dim
    init[:, :d, d] /= scale
    assert seq.origins is not None

    def f32(x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(x, dtype=torch.float32, device=device)

    return Prepared(
        dim=d,
        scale=scale,
        points=f32(np.concatenate(frames)),
        starts=np.r_[0, np.cumsum(counts)].astype(np.int64),
        decoder_points=f32(dec),
        origins=f32(seq.origins / scale),
        init=f32(init),
        centre=f32(init[:, :d, d].mean(0)),
        normals=(
            f32(np.concatenate([losses.frame_normals(f) for f in frames])) if config.loss.chamfer == "plane" else None
        ),
    )


# --------------------------------------------------------------------------------------------
# The model: decoder + latents + occupancy, composed into poses


class StrepModel(torch.nn.Module):
    """Latents (per variant), pose decoder and occupancy MLP of one run.

    ``forward(decoder_points, frames, latents)`` returns correction vectors; the latents
    of the whole sequence are computed once per step by ``self.latents()`` (the chain spans
    every frame, so a batch's loss reaches earlier frames through ``w``).
    """

    def __init__(self, variant: Variant, dim: int, num_frames: int, cfg: ModelConfig) -> None:
        super().__init__()
        self.variant = variant
        latent_dim = latent_size(cfg, dim) if variant != "deepmapping" else 0
        # Built in this order so that every variant draws the same random numbers for the
        # shared networks (the decoder creates its latent layer last).
        self.occupancy = OccupancyMLP(dim, cfg.occupancy_layers)
        self.decoder = PoseDecoder(dim, latent_dim, cfg.point_layers, cfg.head_layers, batch_norm=cfg.batch_norm)
        self.latents = (
            Latents(num_frames, latent_dim, linked=variant == "strep", w_init=cfg.link_init) if latent_dim else None
        )

    def all_latents(self) -> torch.Tensor | None:
        """``(K, b)`` latents of every frame, or ``None`` (deepmapping)."""
        return None if self.latents is None else self.latents()

    def forward(self, decoder_points: torch.Tensor, frames: torch.Tensor, latents: torch.Tensor | None) -> torch.Tensor:
        """Correction vectors ``(B, 3|6)`` of ``frames (B,)`` from their ``(B, Nd, D)`` points."""
        z = None if latents is None else latents.index_select(0, frames)
        return self.decoder(decoder_points, z)


def latent_size(cfg: ModelConfig, dim: int) -> int:
    """Latent dimension: the config's, else 16 in 2D and 24 in 3D (paper)."""
    return cfg.latent_dim if cfg.latent_dim is not None else (16 if dim == 2 else 24)


def _poses(
    model: StrepModel, prep: Prepared, frames: torch.Tensor, latents: torch.Tensor | None, cfg: ModelConfig
) -> torch.Tensor:
    """``(B, D+1, D+1)`` normalised poses of ``frames`` (decoder + composition)."""
    vec = model(prep.decoder_points.index_select(0, frames), frames, latents)
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


def _ragged_indices(starts: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point indices of ``frames`` (in order) and each one's position within ``frames``."""
    n = starts[frames + 1] - starts[frames]
    offs = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    return np.repeat(starts[frames], n) + offs, np.repeat(np.arange(len(frames)), n)


def _sample_per_frame(starts: np.ndarray, frames: np.ndarray, k: int | None, rng: np.random.Generator) -> np.ndarray:
    """Stratified random sample of ``k`` points of every frame (all if it has ``<= k``).

    Frame ``f`` with ``n`` points gets ``floor((j + u_j) n / k)``, ``j < k``, ``u_j ~ U[0, 1)``:
    distinct points spread evenly over the frame's storage order (over the scan angle for
    laser scans), in ``O(k)`` per frame.

    Returns:
        Sorted indices into the batch's concatenated points (frames in the order given).
    """
    n = starts[frames + 1] - starts[frames]
    first = np.r_[0, np.cumsum(n)[:-1]]
    if k is None or k >= n.max():
        return np.arange(int(n.sum()))
    m = np.minimum(n, k)
    j = np.arange(int(m.sum())) - np.repeat(np.cumsum(m) - m, m)
    nn, mm = np.repeat(n, m), np.repeat(m, m)
    pos = np.floor((j + rng.random(len(j))) * (nn / mm)).astype(np.int64)
    return np.repeat(first, m) + np.minimum(pos, nn - 1)


# --------------------------------------------------------------------------------------------
# Batches


def batch_schedule(num_frames: int, batch: int | None, window: int) -> list[np.ndarray]:
    """Contiguous batches of frames covering the sequence, overlapping by ``window`` frames.

    Consecutive batches share ``window`` frames so every temporal neighbour pair lies
    inside at least one batch. ``None`` or ``batch >= num_frames``: one batch of all frames.
    """
    if batch is None or batch >= num_frames:
        return [np.arange(num_frames)]
    stride = max(1, batch - window)
    starts = [*list(range(0, num_frames - batch, stride)), num_frames - batch]
    return [np.arange(s, s + batch) for s in starts]


def _with_partners(frames: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``frames`` plus their spatial partners in ``pairs`` (sorted, unique)."""
    if len(pairs) == 0:
        return frames
    inside = np.isin(pairs[:, 0], frames)
    return np.union1d(frames, pairs[inside, 1])


def _local_pairs(pairs: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Pairs with both frames in ``frames``, renumbered to positions within ``frames``."""
    if len(pairs) == 0:
        return pairs
    ok = np.isin(pairs[:, 0], frames) & np.isin(pairs[:, 1], frames)
    return np.searchsorted(frames, pairs[ok])


# --------------------------------------------------------------------------------------------
# Model artefacts


def save_model(artifact: dict[str, Any], path: str | Path) -> None:
    """Write a model artefact (``MethodOutput.artifacts["model"]``) with `torch.save`."""
    torch.save(artifact, Path(path))


def load_model(path: str | Path) -> dict[str, Any]:
    """Read a model artefact written by `save_model` (tensors and plain values only)."""
    try:
        art = torch.load(Path(path), map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError) as exc:
        raise ConfigError(f"cannot read model {path}: {exc}") from exc
    if not isinstance(art, dict) or art.get("version") != ARTIFACT_VERSION:
        raise ConfigError(f"{path} is not a STREP model artefact (version {ARTIFACT_VERSION})")
    return art


def _artifact(model: StrepModel, prep: Prepared, model_cfg: ModelConfig) -> dict[str, Any]:
    def cpu(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {k: v.detach().cpu().clone() for k, v in sd.items()}

    lat = model.latents
    return {
        "version": ARTIFACT_VERSION,
        "variant": model.variant,
        "dim": prep.dim,
        "scale": prep.scale,
        "model_config": model_cfg.model_dump(),
        "decoder": cpu(model.decoder.state_dict()),
        "occupancy": cpu(model.occupancy.state_dict()),
        "w": None if lat is None or lat.w is None else lat.w.detach().cpu().clone(),
        "latents": None if lat is None else lat.raw.detach().cpu().clone(),
    }


def _load_into(model: StrepModel, art: dict[str, Any]) -> None:
    model.decoder.load_state_dict(art["decoder"])
    model.occupancy.load_state_dict(art["occupancy"])
    if model.latents is not None and model.latents.w is not None:
        if art["w"] is None:
            raise ConfigError("the saved model has no link weight w; it cannot start a linked strep run")
        with torch.no_grad():
            model.latents.w.copy_(art["w"])


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
        loss/ATE history, timings and ``artifacts["model"]`` (see `save_model`).
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
        _load_into(model, art)
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
    total = oc.iterations if optimizer is not None else 0

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
    weak = _weak_matrices(prep) if lc.weak_weight > 0 else None
    base_lrs = [grp["lr"] for grp in optimizer.param_groups] if optimizer else []
    schedule = batch_schedule(k, oc.batch_frames, lc.window)
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
        loops_on = lc.loop_radius is not None and it >= lc.loop_after * total
        if loops_on and (it % oc.pair_interval == 0 or not pairs_found):
            pairs_found = True
            pairs_all = losses.frame_pairs(
                k,
                0,
                positions=current[:, :d, d].detach().cpu().numpy(),
                radius=lc.loop_radius,
                max_per_frame=lc.loop_neighbours,
            )
        frames_np = _with_partners(schedule[it % len(schedule)], pairs_all)
        frames_t = torch.as_tensor(frames_np, device=device)
        clock.lap("batching")

        poses = _poses(model, prep, frames_t, model.all_latents(), model_cfg)
        clock.lap("decoder_forward")

        idx, owner = _ragged_indices(prep.starts, frames_np)
        idx_t, owner_t = torch.as_tensor(idx, device=device), torch.as_tensor(owner, device=device)
        world = _transform(poses, prep.points.index_select(0, idx_t), owner_t)
        terms: dict[str, torch.Tensor] = {}
        if lc.chamfer_weight > 0:
            normals = None
            if prep.normals is not None:  # rotate the local normals with their frames
                rot_only = torch.cat([poses[:, :d, :d], torch.zeros_like(poses[:, :d, d:])], -1)
                normals = _transform(rot_only, prep.normals.index_select(0, idx_t), owner_t)
            query = _sample_per_frame(prep.starts, frames_np, oc.points_per_frame, rng)
            pairs = np.unique(
                np.concatenate([_temporal_pairs(frames_np, lc.window), _local_pairs(pairs_all, frames_np)]),
                axis=0,
            )
            src, target = losses.pair_queries(owner, pairs, query)
            clock.lap("chamfer")
            nn_idx, _ = losses.nearest_in_frame(world.detach().cpu().numpy(), owner, src, target)
            clock.lap("nearest_neighbours")
            # pairs found by proximity (farther apart in time than the window) may use another kernel
            span = np.abs(frames_np[owner[src]] - frames_np[target])
            spatial = span > lc.window
            weight = np.minimum(1.0, lc.window / span) if lc.loop_weight == "span" else None
            kernels = [(~spatial, lc.robust), (spatial, lc.loop_robust or lc.robust)]
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
            delta = poses[:, :d, d] - prep.init.index_select(0, frames_t)[:, :d, d]
            terms["weak"] = torch.einsum("bi,bij,bj->b", delta, weak.index_select(0, frames_t), delta).mean()
        if lc.occupancy_weight > 0:
            # during the warm-up the map learns from the current poses without moving them
            warm = it < lc.occupancy_warmup
            occ_idx = torch.as_tensor(
                _sample_per_frame(prep.starts, frames_np, lc.occupancy_points, occ_rng), device=device
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

        if it % oc.event_interval == 0 or it == total:
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
        chunk = oc.batch_frames or k
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
        artifacts={"model": _artifact(model, prep, model_cfg)},
        timings=timings,
    )


def _weak_matrices(prep: Prepared) -> torch.Tensor:
    """``(K, D, D)`` world-axis penalty matrices of the frames' weak directions at their warm-start
    rotations (`losses.weak_directions`); normals by PCA when the Chamfer term computed none."""
    d = prep.dim
    points = prep.points.detach().cpu().numpy()
    normals = None if prep.normals is None else prep.normals.detach().cpu().numpy()
    local = np.stack(
        [
            losses.weak_directions(
                normals[a:b] if normals is not None else losses.frame_normals(points[a:b].astype(np.float64))
            )
            for a, b in zip(prep.starts[:-1], prep.starts[1:], strict=True)
        ]
    )
    rot = prep.init[:, :d, :d].detach().cpu().double().numpy()
    world = np.einsum("kij,kjl,kml->kim", rot, local, rot)
    return torch.as_tensor(world, dtype=prep.init.dtype, device=prep.init.device)


def _temporal_pairs(frames: np.ndarray, window: int) -> np.ndarray:
    """Ordered pairs of positions ``(a, b)`` in ``frames`` with ``0 < |frames[a] - frames[b]| <= window``."""
    a, b = np.nonzero(np.abs(frames[:, None] - frames[None, :]) <= window)
    keep = a != b
    return np.stack([a[keep], b[keep]], 1).astype(np.int64)
