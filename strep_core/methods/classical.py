"""Classical baselines: identity, incremental ICP, multiway pose graph, KISS-ICP.

Every method takes the initial guess ``init`` ``(K, D+1, D+1)`` (identity or the data's
odometry), keeps frame 0 at ``init[0]`` and returns local -> world poses ``(K, D+1, D+1)``;
2D results are exactly SE(2). Lengths not set in `ClassicalConfig` are derived from the data's
characteristic length ``s = Sequence.scale()`` (median point range; 125 px on v1_pose0, about
2 m on CARMEN scans), so the same defaults work in pixels and metres:

* ``icp``: correspondence distance ``d = 0.16 s`` (20 px on v1_pose0, where 10 px diverges
  because frames move 12 px apart; 0.3 m on CARMEN), in three coarse-to-fine stages
  ``2d, d, d/2``; each frame registered to the union of the 5 previous frames placed by their
  estimates (v1_pose0: 8.3 px frame-to-frame at ``d`` alone, 2.1 px with the three stages,
  1.1 px with the local map); voxel ``0.01 s`` (see `strep_core.registration`).
* ``multiway``: odometry edges from ``icp``; loop closures proposed by proximity of the
  current positions within ``0.8 s`` (100 px on v1_pose0), at least 2 frames apart, 8 nearest
  per frame, kept when their ICP fitness at ``d/2`` reaches 0.6. On 2D keyframes
  (``posegraph.loop_global``, on in the ``laser-keyframes`` profile) the global scan matcher proposes and
  verifies them instead (`strep_core.registration.global_loop_closures`: the 3 nearest earlier
  keyframes within ``3 s`` of every 2nd keyframe, matched over every heading, kept at a score of
  0.6 both ways and a heading within 45 degrees of the chain's, ``posegraph.loop_global_turn``), and
  odometry edges may then be pruned by the line process too.
* ``kiss``: KISS-ICP voxel ``6.5 h``, ``h`` the median nearest-neighbour spacing of the points
  within a frame (`strep_core.registration.point_spacing`): a voxel must gather several points
  of one scan, so sparse 2D scan lines (h = 3 px on v1_pose0: voxel 20 px, 0.16 s) need far
  larger voxels than dense depth images (h = 1.3 cm on 7-Scenes at 1/4 resolution: 8 cm).
  KISS runs on points rescaled so that ``s`` is 10 units (its robust kernel is not unit-free);
  its adaptive-threshold lengths scale with the voxel as in KISS's own defaults (1 m voxel:
  2 m initial threshold, 0.1 m minimum motion); its range limit is the data's largest range.
"""

from __future__ import annotations

import time

import numpy as np

from strep_core import geometry as g
from strep_core import metrics
from strep_core import registration as reg
from strep_core.config import KissConfig, RunConfig
from strep_core.errors import ConfigError
from strep_core.events import IterationEvent, pose_list
from strep_core.methods.base import MethodOutput, RunContext, method
from strep_core.registration.laser_slam import is_planar_laser, laser_slam
from strep_core.sequence import Sequence


@method("identity", description="every frame at its initial guess (identity or odometry); a floor")
def identity_method(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    return MethodOutput(poses=init.copy())


# --------------------------------------------------------------------------------------------
# Progress


class _Progress:
    """Emits `IterationEvent`s every ``interval`` steps (and at the last), checks cancellation.

    Frames not yet placed are shown at the initial guess's relative motion from the last
    placed frame, so every event carries K poses.
    """

    def __init__(self, seq: Sequence, init: np.ndarray, ctx: RunContext, *, total: int, interval: int) -> None:
        self.seq, self.init, self.ctx = seq, init, ctx
        self.total, self.interval = total, interval
        self.history: list[dict[str, float]] = []

    def step(self, iteration: int, poses: np.ndarray, placed: int) -> None:
        """Report ``iteration`` (1-based); ``poses[:placed]`` are estimated, the rest guessed."""
        self.ctx.check_cancel()
        if iteration % self.interval and iteration != self.total:
            return
        current = np.array(poses, dtype=np.float64, copy=True)
        if placed < len(current):
            anchor = current[placed - 1] @ g.inverse(self.init[placed - 1])
            current[placed:] = anchor[None] @ self.init[placed:]
        ate = None
        if self.seq.poses is not None and placed >= 3:
            ate = metrics.ate(current[:placed], self.seq.poses[:placed])
        self.ctx.sink.emit(
            IterationEvent(
                iteration=iteration,
                total=self.total,
                elapsed=self.ctx.elapsed(),
                poses=pose_list(g.pose_to_vector(current)),
                ate=ate,
            )
        )
        self.history.append(
            {"iteration": iteration, "elapsed": self.ctx.elapsed(), **({} if ate is None else {"ate": ate})}
        )


# --------------------------------------------------------------------------------------------
# icp


@method(
    "icp",
    description="incremental point-to-plane ICP (Open3D), each frame to a local map of the previous ones",
)
def icp_method(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    """Incremental point-to-plane ICP; see `strep_core.registration.incremental_icp`."""
    params = reg.resolve_params(seq, config.classical)
    progress = _Progress(seq, init, ctx, total=len(seq), interval=config.classical.event_interval_frames)
    out = reg.incremental_icp(seq, init, params, on_frame=lambda k, poses: progress.step(k + 1, poses, k + 1))
    frames, counts = reg.pair_report(out.pairs)
    return MethodOutput(
        poses=out.poses,
        iterations=len(seq),
        history=progress.history,
        timings={"registration": out.seconds},
        artifacts={"fitness": [p.fitness for p in out.pairs], **frames},
        metrics=counts,
    )


# --------------------------------------------------------------------------------------------
# multiway


@method(
    "multiway",
    description="Open3D pose graph: ICP odometry edges + proximity loop closures, Levenberg-Marquardt",
    total_iterations=lambda seq, cfg: 2 * len(seq),
    counts="steps (each frame's ICP, then its loop closures)",
)
def multiway_method(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    """Multiway registration with an Open3D pose graph.

    Nodes start at the incremental ICP poses; odometry edges (certain, unless
    ``odometry_uncertain``) join consecutive frames; loop-closure edges (uncertain, pruned by the
    line process) join frames whose current positions lie within the loop radius, when their
    ICP fitness reaches ``loop_min_fitness`` (2D with ``loop_global``: found by the global scan
    matcher, `strep_core.registration.global_loop_closures`);
    their ICP starts from the odometry estimate, so it skips the coarsest stage by default
    (``loop_scales``).
    Information matrices come from `get_information_matrix_from_point_clouds`. 2D runs in 3D
    at ``z = 0`` and the result is projected onto SE(2).
    """
    cfg = config.classical.posegraph
    if cfg.frontend == "submaps" or (cfg.frontend == "auto" and is_planar_laser(seq)):
        return _laser_multiway(seq, init, config, ctx)
    params = reg.resolve_params(seq, config.classical)
    k_frames = len(seq)
    progress = _Progress(seq, init, ctx, total=2 * k_frames, interval=config.classical.event_interval_frames)
    odo = reg.incremental_icp(seq, init, params, on_frame=lambda k, poses: progress.step(k + 1, poses, k + 1))
    clouds = odo.clouds
    radius = cfg.loop_radius if cfg.loop_radius is not None else cfg.loop_radius_fraction * seq.scale()
    fine = params.max_correspondence * min(params.scales)
    loop_scales = tuple(cfg.loop_scales) if cfg.loop_scales is not None else params.scales[1:] or params.scales

    use_global = seq.dim == 2 and params.global_match is not None and cfg.loop_global != "off"
    robust_odometry = cfg.odometry_uncertain == "on" or (cfg.odometry_uncertain == "auto" and use_global)
    on_frame = lambda j: progress.step(k_frames + j, odo.poses, k_frames)  # noqa: E731
    t0 = time.perf_counter()
    with reg.open3d_quiet(params.threads):
        if use_global:
            # the global matcher proposes and verifies: a drifted chain still closes its loops
            loops, tried = reg.global_loop_closures(
                clouds,
                odo.poses,
                params,
                radius=cfg.loop_global_radius * seq.scale(),
                min_gap=max(cfg.loop_min_gap, config.classical.icp.local_map_frames + 1),
                min_score=cfg.loop_global_score,
                min_fitness=cfg.loop_min_fitness,
                max_per_frame=cfg.loop_global_candidates,
                every=cfg.loop_global_every,
                scales=loop_scales,
                max_turn=float(np.radians(cfg.loop_global_turn)),
                on_frame=on_frame,
            )
        else:
            candidates = reg.loop_candidates(
                g.translation(odo.poses), radius=radius, min_gap=cfg.loop_min_gap, max_per_frame=cfg.loop_max_candidates
            )
            tried = len(candidates)
            loops = reg.proximity_loop_closures(
                clouds,
                odo.poses,
                candidates,
                params,
                scales=loop_scales,
                min_fitness=cfg.loop_min_fitness,
                on_frame=on_frame,
            )
        t_loops = time.perf_counter() - t0

        ctx.check_cancel()
        t1 = time.perf_counter()
        optimised, edges = reg.optimise_pose_graph(
            clouds,
            odo.poses,
            loops,
            distance=fine,
            odometry_uncertain=robust_odometry,
            edge_prune_threshold=cfg.edge_prune_threshold,
            loop_preference=cfg.loop_preference,
        )
        t_opt = time.perf_counter() - t1
    poses = reg.from_se3(optimised, seq.dim)  # node 0 (the reference) stays at init[0]
    frames, counts = reg.pair_report(odo.pairs)
    progress.step(2 * k_frames, poses, k_frames)
    return MethodOutput(
        poses=poses,
        iterations=2 * k_frames,
        history=progress.history,
        timings={"registration": odo.seconds, "loop_closure": t_loops, "optimization": t_opt},
        artifacts={
            "loop_candidates": tried,
            "loop_source": "global scan matcher" if use_global else "proximity",
            "loop_edges": len(loops),
            "graph_edges": edges,
            **frames,
        },
        metrics=counts,
    )


def _laser_multiway(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    """``multiway`` on planar laser scans: `strep_core.registration.laser_slam`."""
    if seq.dim != 2:
        raise ConfigError("classical.posegraph.frontend=submaps registers planar (2D) scans only")
    k_frames = len(seq)
    progress = _Progress(seq, init, ctx, total=2 * k_frames, interval=config.classical.event_interval_frames)
    state: dict[str, np.ndarray] = {}

    def on_scan(k: int, poses: np.ndarray) -> None:
        state["poses"] = poses
        progress.step(k + 1, poses, k + 1)

    def on_loop_search(k: int) -> None:
        progress.step(k_frames + k + 1, state["poses"], k_frames)

    out = laser_slam(seq, init[0], on_scan=on_scan, on_loop_search=on_loop_search)
    progress.step(2 * k_frames, out.poses, k_frames)
    verdicts = out.verdicts()
    return MethodOutput(
        poses=out.poses,
        iterations=2 * k_frames,
        history=progress.history,
        timings=out.timings,
        artifacts={
            "loop_candidates": out.loops_tried,
            "loop_source": "submaps",
            "loop_edges": len(out.loops),
            "loop_passes": len(out.loop_passes),
            "matches": out.report(),
        },
        metrics={
            "matches_failed": verdicts["failed"],
            "matches_ambiguous": verdicts["ambiguous"],
            "loops_kept": out.loops_kept,
            "loops_rejected": len(out.loops) - out.loops_kept,
            "loops_inconsistent": out.loops_inconsistent,
            "spacing_priors": len(out.priors),
        },
    )


# --------------------------------------------------------------------------------------------
# kiss


def kiss_settings(seq: Sequence, cfg: KissConfig) -> dict[str, float]:
    """KISS-ICP settings for ``seq``, in KISS's internal unit (see `kiss_method`).

    Returns ``unit`` (sequence units per KISS unit: ``scale / reference_scale``), and in
    KISS units: ``voxel`` (``voxel`` or ``voxel_spacing * point_spacing``), ``max_range``
    (the data's largest point range: KISS drops map points farther than it from the sensor and
    weighs rotation errors by it), ``initial_threshold`` and ``min_motion`` (KISS's defaults
    for its 1 m voxel, 2 m and 0.1 m, scaled by the voxel).
    """
    assert seq.origins is not None
    scale = seq.scale()
    unit = scale / cfg.reference_scale
    voxel = (cfg.voxel if cfg.voxel is not None else cfg.voxel_spacing * reg.point_spacing(seq)) / unit
    max_range = max(float(np.linalg.norm(f - o, axis=1).max()) for f, o in zip(seq.frames, seq.origins, strict=True))
    return {
        "unit": unit,
        "voxel": voxel,
        "max_range": 1.01 * max(max_range / unit, voxel),
        "initial_threshold": cfg.initial_threshold * voxel,
        "min_motion": cfg.min_motion * voxel,
    }


@method("kiss", description="KISS-ICP 1.3 odometry (point-to-point to a voxel map, adaptive threshold)")
def kiss_method(seq: Sequence, init: np.ndarray, config: RunConfig, ctx: RunContext) -> MethodOutput:
    """KISS-ICP on the frames (2D as ``z = 0`` points), deskewing off.

    KISS's robust kernel weighs a residual r by ``k^2 / (k + r^2)^2``: it mixes a length with a
    squared length, so KISS does not behave the same in pixels and in metres. Frames are
    therefore divided by ``unit = scale / kiss.reference_scale`` (the data's median range
    becomes 10 units, as for the LiDARs KISS was tuned on) and translations multiplied back.
    On v1_pose0 most voxels between 0.11 and 0.22 of the scale then give 0.7 to 3 px, where
    the same voxels in raw pixels land anywhere between 20 and 400 px. KISS stays chaotic on
    this sparse synthetic data: about one setting in ten near the default drifts to 15-20 px
    after losing a few frames around frame 150.

    KISS predicts each frame's motion with its constant-velocity model. With
    ``kiss.prior="init"`` (or ``"auto"`` when the initial guess moves: odometry), the guess's
    relative motion ``init[k-1]^-1 init[k]`` replaces that prediction before each frame. Its
    trajectory starts at identity and is composed with ``init[0]``.
    """
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import AdaptiveThresholdConfig, DataConfig, MappingConfig, RegistrationConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = config.classical.kiss
    st = kiss_settings(seq, cfg)
    kiss_cfg = KISSConfig(
        data=DataConfig(max_range=st["max_range"], min_range=0.0, deskew=False),
        mapping=MappingConfig(voxel_size=st["voxel"], max_points_per_voxel=cfg.max_points_per_voxel),
        registration=RegistrationConfig(max_num_threads=config.classical.threads),
        adaptive_threshold=AdaptiveThresholdConfig(
            initial_threshold=st["initial_threshold"], min_motion_th=st["min_motion"]
        ),
    )
    init3 = g.to_se3(init)
    rel = g.relative(init3[:-1], init3[1:])
    moving = bool(np.abs(rel - np.eye(4)).max() > 1e-12)
    use_init = cfg.prior == "init" or (cfg.prior == "auto" and moving)

    odometry = KissICP(kiss_cfg)
    progress = _Progress(seq, init, ctx, total=len(seq), interval=config.classical.event_interval_frames)
    poses3 = np.repeat(np.eye(4)[None], len(seq), axis=0)
    stamps = np.zeros(0)
    t0 = time.perf_counter()
    for k, frame in enumerate(seq.frames):
        if use_init and k > 0:
            prior = rel[k - 1].copy()
            prior[:3, 3] /= st["unit"]
            odometry.last_delta = prior
        odometry.register_frame(g.pad_points(frame) / st["unit"], stamps)
        delta = np.array(odometry.last_pose, dtype=np.float64)
        delta[:3, 3] *= st["unit"]
        poses3[k] = init3[0] @ delta
        if seq.dim == 2:
            poses3[k] = reg.project_planar(poses3[k])
        progress.step(k + 1, reg.from_se3(poses3, seq.dim), k + 1)
    seconds = time.perf_counter() - t0
    return MethodOutput(
        poses=reg.from_se3(poses3, seq.dim),
        iterations=len(seq),
        history=progress.history,
        timings={"registration": seconds},
        artifacts={"kiss": {**st, "prior": "init" if use_init else "velocity"}},
    )
