"""The sections of the run config, one per concern: classical baselines, model, loss,
optimiser, reader options. `strep_core.config` composes them into `RunConfig` (and re-exports
them: import them from there)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

# A layer width, and the most points any per-frame count may ask for: bounds that keep a
# request from allocating terabytes in a worker (the defaults are far below them).
Width = Annotated[int, Field(ge=1, le=4096)]
MAX_POINTS = 1_000_000


class Section(BaseModel):
    """A section of the run config: unknown fields, NaN and infinity refused, assignments validated."""

    # allow_inf_nan=False: Infinity/NaN (which JSON bodies may carry) are refused, never stored as null
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


# ---- classical baselines -------------------------------------------------------------------


class ClassicalConfig(Section):
    """Settings of the classical baselines (`icp`, `multiway`, `kiss`).

    Lengths left at ``None`` are derived from the data as ``fraction * Sequence.scale()``
    (the median point range), so one set of defaults serves pixels and metres; see
    `strep_core.registration` and `strep_core.methods.classical` for the rules.
    """

    # ---- ICP (icp, multiway's edges)
    max_correspondence: float | None = Field(
        default=None, gt=0, description="ICP correspondence distance (sequence unit); None: from data"
    )
    correspondence_fraction: float = Field(
        default=0.16, gt=0, le=10, description="correspondence distance = this * scale when not given"
    )
    icp_scales: list[float] = Field(
        default=[2.0, 1.0, 0.5],
        min_length=1,
        max_length=16,
        description="coarse-to-fine ICP stages, multipliers of the correspondence distance",
    )
    icp_iterations: int = Field(default=50, ge=1, le=1000, description="ICP iterations per stage")
    icp_min_fitness: float = Field(
        default=0.1, ge=0, le=1, description="discard an ICP stage matching fewer source points than this"
    )
    icp_kernel: float | None = Field(
        default=None, gt=0, le=10, description="Tukey kernel width, fraction of the stage's distance; None: L2"
    )
    icp_yaw_search: float = Field(
        default=0.0,
        ge=0,
        le=180,
        description="ICP: also start the coarsest stage from the guess turned about the sensor's vertical "
        "axis by up to +-this many degrees (every icp_yaw_step) and keep the best match; in 3D only with "
        "icp_yaw_axis; 0: the guess alone",
    )
    icp_motion_prior: Literal["init", "velocity"] = Field(
        default="init",
        description="incremental ICP's guess for each pair: the initial guess's relative motion, or the "
        "previous pair's estimated motion (constant velocity)",
    )
    icp_yaw_step: float = Field(default=10.0, gt=0, le=180, description="ICP yaw search step (degrees)")
    icp_yaw_axis: tuple[float, float, float] | None = Field(
        default=None,
        description="3D ICP: the sensor's vertical axis in its own frame, about which the yaw search turns "
        "(e.g. [0, -1, 0] for a level camera with OpenCV axes, [0, 0, 1] for a level LiDAR); None: no yaw "
        "search in 3D (2D always turns about z)",
    )
    icp_correlative: float = Field(
        default=0.0,
        ge=0,
        le=100,
        description="2D ICP: also start from a correlative scan match (an exhaustive yaw and translation "
        "search on a likelihood field) within +-this many correspondence distances and +-icp_correlative_yaw "
        "degrees of the guess, and keep it when it matches more points; 0: off",
    )
    icp_correlative_yaw: float = Field(
        default=60.0, gt=0, le=180, description="correlative scan match: yaw window (degrees, 1 degree steps)"
    )
    icp_global: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="ICP: also start each consecutive pair from a global scan match (branch and bound over every "
        "heading and +-icp_global_window * scale, `strep_core.scanmatch`) and keep it when ICP from there matches "
        "more points; auto: on for 2D sequences (planar scans), off in 3D",
    )
    icp_global_window: float = Field(
        default=1.5, gt=0, le=20, description="global scan match: translation window, fraction of the scale"
    )
    icp_global_resolution: float = Field(
        default=0.025, gt=0, le=1, description="global scan match: finest grid cell, fraction of the scale"
    )
    icp_global_yaw_step: float = Field(
        default=1.0, gt=0, le=30, description="global scan match: finest yaw step (degrees)"
    )
    icp_global_yaw_window: float = Field(
        default=180.0,
        gt=0,
        le=180,
        description="global scan match of consecutive pairs: headings within +-this many degrees of the guess's "
        "(180: the full circle; loop closures always search the full circle)",
    )
    icp_global_range: float = Field(
        default=8.0, gt=0, le=1000, description="global scan match: source points within this fraction of the scale"
    )
    icp_global_prior: float = Field(
        default=0.2,
        ge=0,
        le=10,
        description="global scan match: score lost (mean likelihood, 0 to 1) by a translation one scale away "
        "from the previous pair's (quadratic): breaks the ties of corridors in favour of steady motion; 0: none",
    )
    icp_global_prior_stop: float = Field(
        default=0.1,
        ge=0,
        le=10,
        description="global scan match: a step prior (median of the last steps) shorter than this fraction of the "
        "scale is a stop (turns in place): the median of the last longer steps replaces it "
        "(docs/design/scan-matching.md, fourth part); 0: never",
    )
    icp_degeneracy: float = Field(
        default=0.0,
        ge=0,
        le=0.5,
        description="keep the guess's translation along directions that the matched target normals constrain "
        "weakly: smallest eigenvalues of their mean outer product below this (a view of one wall, a corridor); "
        "0: off",
    )
    local_map_frames: int = Field(
        default=5, ge=1, le=50, description="icp: register each frame to the union of this many previous ones"
    )
    voxel: float | None = Field(
        default=None, ge=0, description="voxel size for downsampling (sequence unit; 0: none); None: from data"
    )
    voxel_fraction: float = Field(default=0.01, ge=0, le=1, description="voxel = this * scale when not given")
    normal_neighbours: int = Field(default=6, ge=2, le=100, description="2D normals: PCA neighbourhood size")
    normal_radius: float | None = Field(
        default=None, gt=0, description="3D normals: search radius (sequence unit); None: from data"
    )
    normal_radius_factor: float = Field(
        default=2.0, gt=0, le=100, description="3D normal radius = this * max(voxel, point spacing) when not given"
    )
    normal_max_nn: int = Field(default=30, ge=3, le=1000, description="3D normals: at most this many neighbours")
    # ---- multiway pose graph
    loop_radius: float | None = Field(
        default=None, gt=0, description="multiway: loop-closure search radius (sequence unit); None: from data"
    )
    loop_radius_fraction: float = Field(
        default=0.8, gt=0, le=100, description="loop radius = this * scale when not given"
    )
    loop_min_gap: int = Field(
        default=2, ge=2, le=10_000, description="loop closures only between frames at least this far apart"
    )
    loop_min_fitness: float = Field(default=0.6, ge=0, le=1, description="keep a loop edge above this ICP fitness")
    loop_max_candidates: int = Field(default=8, ge=0, le=100, description="loop edges tried per frame")
    loop_scales: list[float] | None = Field(
        default=None,
        min_length=1,
        max_length=16,
        description="ICP stages of loop-closure edges; None: icp_scales without its coarsest stage",
    )
    edge_prune_threshold: float = Field(
        default=0.25, ge=0, le=1, description="pose graph: line-process weight below which a loop edge is pruned"
    )
    loop_preference: float = Field(
        default=1.0,
        gt=0,
        le=100,
        description="pose graph: Open3D's preference_loop_closure (below 1: trust odometry edges more, above 1: "
        "loop closures more)",
    )
    loop_global: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="multiway, 2D: loop closures proposed by the global scan matcher (each keyframe against earlier "
        "ones within loop_global_radius * scale of its estimate, accepted above loop_global_score, refined by ICP) "
        "instead of by proximity alone; auto: on for 2D sequences when icp_global is on",
    )
    loop_global_radius: float = Field(
        default=3.0, gt=0, le=100, description="global loop closures: search radius, fraction of the scale"
    )
    loop_global_score: float = Field(
        default=0.6, ge=0, le=1, description="global loop closures: least matcher score (mean likelihood) to accept"
    )
    odometry_uncertain: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="multiway: odometry edges may be pruned by the line process like loop closures (a wrong "
        "consecutive match then yields to the loops around it); auto: on with the global loop closures",
    )
    loop_global_every: int = Field(
        default=2, ge=1, le=1000, description="global loop closures: try every this many frames"
    )
    loop_global_candidates: int = Field(
        default=3, ge=0, le=100, description="global loop closures: earlier frames tried per frame, nearest first"
    )
    loop_global_turn: float = Field(
        default=45.0,
        gt=0,
        le=180,
        description="global loop closures: reject a loop whose relative heading differs from the chain's estimate by "
        "more than this many degrees (corridors look alike after a half turn, square rooms after a quarter turn; "
        "180: off); docs/design/scan-matching.md, third part",
    )
    # ---- KISS-ICP
    kiss_voxel: float | None = Field(
        default=None, gt=0, description="KISS-ICP voxel size (sequence unit); None: from data"
    )
    kiss_voxel_spacing: float = Field(
        default=6.5, gt=0, le=1000, description="KISS voxel = this * median point spacing when not given"
    )
    kiss_reference_scale: float = Field(
        default=10.0,
        gt=0,
        description="KISS runs on points rescaled so that the data's scale equals this many units "
        "(its robust kernel is not unit-free; 10: a LiDAR's median range in metres, as KISS is tuned)",
    )
    kiss_max_points_per_voxel: int = Field(default=20, ge=1, le=1000, description="KISS map points per voxel")
    kiss_initial_threshold: float = Field(
        default=2.0, gt=0, le=100, description="KISS adaptive threshold before motion is seen, in voxels"
    )
    kiss_min_motion: float = Field(
        default=0.1, ge=0, le=100, description="KISS: motions below this many voxels do not update the threshold"
    )
    kiss_prior: Literal["auto", "velocity", "init"] = Field(
        default="auto",
        description="KISS motion prediction: its constant-velocity model, the initial guess's relative "
        "motion, or auto (the guess when it moves, else constant velocity)",
    )
    # ---- all
    event_interval: int = Field(default=10, ge=1, description="emit an iteration event every N frames")
    threads: int = Field(
        default=1, ge=1, le=256, description="CPU threads for Open3D and KISS-ICP (1: bit-for-bit repeatable)"
    )

    @field_validator("icp_yaw_axis")
    @classmethod
    def _axis_nonzero(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is not None and sum(c * c for c in v) < 1e-12:
            raise ValueError("icp_yaw_axis must be a nonzero vector")
        return v


# ---- learned methods (strep, strep-nolink, deepmapping) ------------------------------------


class ModelConfig(Section):
    """Networks of the learned methods: widths are the paper's, other defaults measured
    (see `strep_core.optimize`)."""

    latent_dim: int | None = Field(default=None, ge=1, le=512, description="None: 16 in 2D, 24 in 3D")
    planar_axis: list[float] | None = Field(
        default=None,
        min_length=3,
        max_length=3,
        description="3D, a level camera: pose corrections turn only about this axis and move across it "
        "(departure: the paper regresses 6 DoF); None: 6 DoF",
    )
    point_layers: list[Width] = Field(
        default=[64, 256, 1024], min_length=1, max_length=16, description="per-point layers of the pose decoder"
    )
    head_layers: list[Width] = Field(
        default=[512, 128], max_length=16, description="fully connected layers after max-pooling"
    )
    occupancy_layers: list[Width] = Field(
        default=[64, 256, 512, 256, 128], min_length=1, max_length=16, description="hidden layers of the occupancy MLP"
    )
    batch_norm: bool = Field(
        default=False,
        description="BatchNorm after every decoder layer (couples the frames of a batch; the final "
        "pass then uses batch statistics too)",
    )
    link_init: float = Field(
        default=0.5,
        ge=-1,
        le=1,
        description="initial value of every entry of the temporal link weight w (strep only)",
    )
    decoder_points: int | None = Field(
        default=16,
        ge=8,
        le=MAX_POINTS,
        description="points per frame fed to the pose decoder: a fixed, evenly strided subset "
        "(the same at every step and in the final pass); None: all points",
    )
    composition: Literal["local", "world"] = Field(
        default="world",
        description="local: pose = warm start @ correction; world: correction rotates about the "
        "sensor and translates along world axes",
    )
    translation_scale: float = Field(
        default=1.0, gt=0, description="decoder translation output x this x sequence scale = correction"
    )


class LossConfig(Section):
    """Loss terms of the learned methods (defaults measured, see `strep_core.optimize`).

    Thresholds and radii are fractions of the sequence's scale (`Sequence.scale`).
    """

    chamfer_weight: float = Field(default=1.0, ge=0)
    occupancy_weight: float = Field(default=0.0, ge=0)
    weak_weight: float = Field(
        default=0.0,
        ge=0,
        description="penalty on a frame's translation correction (scale units, squared) along the directions its "
        "own normals constrain weakly, 1 - eigenvalue / largest of their scatter (a corridor's axis); 0: off "
        "(docs/design/warm-start.md, weak directions)",
    )
    window: int = Field(default=2, ge=1, le=64, description="Chamfer to neighbours within +-window frames")
    loop_radius: float | None = Field(
        default=0.5,
        gt=0,
        description="also Chamfer to frames farther apart in time whose sensors are closer than this "
        "(x scale) in the current estimate; None: temporal neighbours only",
    )
    loop_neighbours: int = Field(default=8, ge=1, le=64, description="spatial neighbours per frame at most")
    loop_after: float = Field(
        default=0.0,
        ge=0,
        le=1,
        description="spatial (loop) pairs join the Chamfer term only after this fraction of the iterations "
        "(from scratch the trajectory has to form before positions mean anything)",
    )
    chamfer: Literal["point", "plane"] = Field(
        default="plane",
        description="point: squared point-to-point distances (paper); plane: distances along the "
        "matched point's normal (PCA of its neighbours in its frame)",
    )
    robust: Literal["none", "truncated", "huber", "trimmed"] = Field(
        default="truncated",
        description="none: squared distances (paper); truncated: min(d^2, threshold^2); huber; "
        "trimmed: squared distances of the trim_keep fraction of each pair's closest matches",
    )
    trim_keep: float = Field(default=0.5, gt=0, le=1, description="trimmed: fraction of each pair's matches kept")
    loop_robust: Literal["none", "truncated", "huber"] | None = Field(
        default=None,
        description="robust kernel of the spatial (loop) pairs; None: robust. A pair found by proximity overlaps "
        "partly: truncated distances give the unmatched part no pull",
    )
    loop_weight: Literal["uniform", "span"] = Field(
        default="uniform",
        description="weight of a spatial pair's matches: uniform, or span = window / (frames between the pair), "
        "so that a loop spanning n frames of a linked chain pulls each of its n increments no harder than a "
        "temporal pair does (docs/design/from-scratch.md)",
    )
    threshold: float = Field(default=0.02, gt=0, description="robust threshold (x scale; at the end if annealed)")
    threshold_start: float | None = Field(
        default=0.1, gt=0, description="robust threshold (x scale) at the start, annealed geometrically; None: constant"
    )
    free_samples: int = Field(default=1, ge=0, le=64, description="free-space samples per ray")
    occupancy_points: int = Field(
        default=16, ge=1, le=MAX_POINTS, description="rays (observed points) per frame per step"
    )
    occupancy_warmup: int = Field(
        default=0,
        ge=0,
        le=100_000,
        description="first N iterations: the occupancy MLP learns the map, poses get no gradient from it",
    )


class OptimConfig(Section):
    """The per-sequence optimisation of the learned methods (see `strep_core.optimize`)."""

    iterations: int = Field(default=300, ge=0, le=100_000)
    lr_network: float = Field(default=1e-3, gt=0, le=1, description="Adam lr of decoder, occupancy MLP and w")
    lr_latent: float = Field(default=1e-4, gt=0, le=1, description="Adam lr of the latent vectors (paper)")
    lr_latent_frozen: float = Field(
        default=0.1,
        gt=0,
        le=10,
        description="Adam lr of the latents when from_model + freeze re-optimise only them "
        "(1e-4 barely moves N(0, 1) latents in a few hundred steps)",
    )
    schedule: Literal["constant", "cosine"] = Field(default="cosine", description="learning-rate schedule")
    final_lr_fraction: float = Field(default=0.05, ge=0, le=1, description="cosine: final lr / initial lr")
    warmup_iterations: int = Field(
        default=0, ge=0, le=100_000, description="learning rates rise linearly from 0 over this many first steps"
    )
    batch_frames: Annotated[int, Field(ge=2, le=MAX_POINTS)] | Literal["auto"] | None = Field(
        default="auto",
        description="frames per step: batches overlapping by the Chamfer window, each visited `iterations` times; "
        "auto: all frames up to 256, longer sequences in batches of 256 (docs/design/whole-logs.md); None: all",
    )
    points_per_frame: int | None = Field(
        default=32, ge=8, le=MAX_POINTS, description="query points per frame per step for Chamfer; None: all"
    )
    max_points_per_frame: int = Field(
        default=4096,
        ge=16,
        le=MAX_POINTS,
        description="working set: frames with more points keep a fixed random subset",
    )
    pair_interval: int = Field(default=10, ge=1, description="recompute spatial neighbours every N iterations")
    event_interval: int = Field(default=5, ge=1, description="emit an iteration event every N iterations")


class DataConfig(Section):
    """Reader options (`strep_core.io.load_sequence`): ``None`` leaves the reader's default;
    an option the input's format does not take is refused."""

    stride: int | None = Field(default=None, ge=1, le=64, description="depth images: keep every stride-th pixel")
    max_range: float | None = Field(default=None, gt=0, description="laser logs: drop ranges at or beyond (m)")
    max_depth: float | None = Field(default=None, gt=0, description="depth images: drop points farther (m)")
    depth_scale: float | None = Field(default=None, gt=0, description="depth images: raw units per metre")
    intrinsics: list[float] | None = Field(
        default=None, min_length=4, max_length=4, description="depth images: fx, fy, cx, cy in pixels"
    )
    voxel: float | None = Field(default=None, gt=0, description="point-cloud folders: voxel downsampling")

    def options(self) -> dict[str, Any]:
        """The options given, as keyword arguments of the reader."""
        return {k: v for k, v in self.model_dump().items() if v is not None}
