"""The classical baselines' section of the run config, ``classical``, nested by concern:
``icp``, ``correlative``, ``scanmatch``, ``normals``, ``posegraph``, ``kiss`` (one name per
setting, no prefixes; docs/design/extending.md, "Configuration"). `strep_core.config` composes
it into `RunConfig` and re-exports it.

Lengths left at ``None`` are derived from the data as ``fraction * Sequence.scale()`` (the
median point range), so one set of defaults serves pixels and metres; see
`strep_core.registration` and `strep_core.methods.classical` for the rules.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from strep_core.config.sections import Section


class IcpConfig(Section):
    """Pairwise ICP (``icp``, the pose graph's edges, the learned methods' warm start)."""

    max_correspondence: float | None = Field(
        default=None, gt=0, description="ICP correspondence distance (sequence unit); None: from data"
    )
    correspondence_fraction: float = Field(
        default=0.16, gt=0, le=10, description="correspondence distance = this * scale when not given"
    )
    scales: list[float] = Field(
        default=[2.0, 1.0, 0.5],
        min_length=1,
        max_length=16,
        description="coarse-to-fine ICP stages, multipliers of the correspondence distance",
    )
    iterations: int = Field(default=50, ge=1, le=1000, description="ICP iterations per stage")
    min_fitness: float = Field(
        default=0.1, ge=0, le=1, description="discard an ICP stage matching fewer source points than this"
    )
    kernel: float | None = Field(
        default=None, gt=0, le=10, description="Tukey kernel width, fraction of the stage's distance; None: L2"
    )
    yaw_search: float = Field(
        default=0.0,
        ge=0,
        le=180,
        description="ICP: also start the coarsest stage from the guess turned about the sensor's vertical "
        "axis by up to +-this many degrees (every yaw_step) and keep the best match; in 3D only with "
        "yaw_axis; 0: the guess alone",
    )
    motion_prior: Literal["init", "velocity"] = Field(
        default="init",
        description="incremental ICP's guess for each pair: the initial guess's relative motion, or the "
        "previous pair's estimated motion (constant velocity)",
    )
    yaw_step: float = Field(default=10.0, gt=0, le=180, description="ICP yaw search step (degrees)")
    yaw_axis: tuple[float, float, float] | None = Field(
        default=None,
        description="3D ICP: the sensor's vertical axis in its own frame, about which the yaw search turns "
        "(e.g. [0, -1, 0] for a level camera with OpenCV axes, [0, 0, 1] for a level LiDAR); None: no yaw "
        "search in 3D (2D always turns about z)",
    )
    search_voxel: float = Field(
        default=1.0,
        ge=1,
        le=20,
        description="3D ICP: the yaw search's starts run on the clouds downsampled to this many voxels (cheaper); "
        "1: on the clouds as prepared",
    )
    yaw_refine: float = Field(
        default=0.0,
        ge=0,
        le=60,
        description="3D ICP: before the yaw search, move yaw_axis to the mean of the source's normals within this "
        "many degrees of it (its floor and ceiling: a hand-held LiDAR tilts); 0: off",
    )
    yaw_verify: float = Field(
        default=0.0,
        ge=0,
        le=10,
        description="3D ICP: when the yaw search's best start leaves a trimmed distance above this many voxels "
        "(of the clouds the search ran on), try every other heading too; 0: off",
    )
    degeneracy: float = Field(
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

    @field_validator("yaw_axis")
    @classmethod
    def _axis_nonzero(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is not None and sum(c * c for c in v) < 1e-12:
            raise ValueError("yaw_axis must be a nonzero vector")
        return v


class CorrelativeConfig(Section):
    """2D: the correlative scan match (`strep_core.correlative`) as a further ICP start."""

    window: float = Field(
        default=0.0,
        ge=0,
        le=100,
        description="2D ICP: also start from a correlative scan match (an exhaustive yaw and translation "
        "search on a likelihood field) within +-this many correspondence distances and +-yaw_window "
        "degrees of the guess, and keep it when it matches more points; 0: off",
    )
    yaw_window: float = Field(
        default=60.0, gt=0, le=180, description="correlative scan match: yaw window (degrees, 1 degree steps)"
    )


class ScanMatchConfig(Section):
    """2D: the global scan matcher (`strep_core.scanmatch`) on consecutive pairs. Lengths are
    fractions of the scale."""

    consecutive: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="ICP: also start each consecutive pair from a global scan match (branch and bound over every "
        "heading and +-window * scale, `strep_core.scanmatch`) and keep it when ICP from there matches "
        "more points; auto: on for 2D sequences (planar scans), off in 3D",
    )
    window: float = Field(
        default=1.5, gt=0, le=20, description="global scan match: translation window, fraction of the scale"
    )
    resolution: float = Field(
        default=0.025, gt=0, le=1, description="global scan match: finest grid cell, fraction of the scale"
    )
    yaw_step: float = Field(default=1.0, gt=0, le=30, description="global scan match: finest yaw step (degrees)")
    yaw_window: float = Field(
        default=180.0,
        gt=0,
        le=180,
        description="global scan match of consecutive pairs: headings within +-this many degrees of the guess's "
        "(180: the full circle; loop closures always search the full circle)",
    )
    range: float = Field(
        default=8.0, gt=0, le=1000, description="global scan match: source points within this fraction of the scale"
    )
    prior: float = Field(
        default=0.2,
        ge=0,
        le=10,
        description="global scan match: score lost (mean likelihood, 0 to 1) by a translation one scale away "
        "from the previous pair's (quadratic): breaks the ties of corridors in favour of steady motion; 0: none",
    )
    prior_stop: float = Field(
        default=0.1,
        ge=0,
        le=10,
        description="global scan match: a step prior (median of the last steps) shorter than this fraction of the "
        "scale is a stop (turns in place): the median of the last longer steps replaces it "
        "(docs/design/scan-matching.md, fourth part); 0: never",
    )


class NormalsConfig(Section):
    """Point normals for point-to-plane ICP."""

    neighbours: int = Field(default=6, ge=2, le=100, description="2D normals: PCA neighbourhood size")
    radius: float | None = Field(
        default=None, gt=0, description="3D normals: search radius (sequence unit); None: from data"
    )
    radius_factor: float = Field(
        default=2.0, gt=0, le=100, description="3D normal radius = this * max(voxel, point spacing) when not given"
    )
    max_nn: int = Field(default=30, ge=3, le=1000, description="3D normals: at most this many neighbours")


class PoseGraphConfig(Section):
    """The ``multiway`` pose graph: loop closures and the graph optimisation."""

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
        description="ICP stages of loop-closure edges; None: icp.scales without its coarsest stage",
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
    frontend: Literal["auto", "submaps", "icp"] = Field(
        default="auto",
        description="multiway: submaps = planar-laser SLAM (each scan against a submap, verified loops against "
        "finished submaps, a robust GTSAM graph; docs/design/laser-slam.md); icp = the incremental ICP chain and "
        "Open3D's pose graph; auto: submaps for planar laser scans, icp otherwise",
    )
    loop_global: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="multiway, 2D: loop closures proposed by the global scan matcher (each keyframe against earlier "
        "ones within loop_global_radius * scale of its estimate, accepted above loop_global_score, refined by ICP) "
        "instead of by proximity alone; auto: on for 2D sequences when scanmatch.consecutive is on",
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


class KissConfig(Section):
    """KISS-ICP (``kiss``)."""

    voxel: float | None = Field(default=None, gt=0, description="KISS-ICP voxel size (sequence unit); None: from data")
    voxel_spacing: float = Field(
        default=6.5, gt=0, le=1000, description="KISS voxel = this * median point spacing when not given"
    )
    reference_scale: float = Field(
        default=10.0,
        gt=0,
        description="KISS runs on points rescaled so that the data's scale equals this many units "
        "(its robust kernel is not unit-free; 10: a LiDAR's median range in metres, as KISS is tuned)",
    )
    max_points_per_voxel: int = Field(default=20, ge=1, le=1000, description="KISS map points per voxel")
    initial_threshold: float = Field(
        default=2.0, gt=0, le=100, description="KISS adaptive threshold before motion is seen, in voxels"
    )
    min_motion: float = Field(
        default=0.1, ge=0, le=100, description="KISS: motions below this many voxels do not update the threshold"
    )
    prior: Literal["auto", "velocity", "init"] = Field(
        default="auto",
        description="KISS motion prediction: its constant-velocity model, the initial guess's relative "
        "motion, or auto (the guess when it moves, else constant velocity)",
    )


class ClassicalConfig(Section):
    """Settings of the classical baselines (`icp`, `multiway`, `kiss`), one sub-section per concern.

    The flat names of version 1 (``icp_scales``, ``kiss_voxel``...) are still read from files of
    that version (`strep_core.config.migrate`).
    """

    icp: IcpConfig = Field(default_factory=IcpConfig, description="pairwise ICP")
    correlative: CorrelativeConfig = Field(
        default_factory=CorrelativeConfig, description="2D: correlative scan match as an ICP start"
    )
    scanmatch: ScanMatchConfig = Field(
        default_factory=ScanMatchConfig, description="2D: global scan match of consecutive pairs"
    )
    normals: NormalsConfig = Field(default_factory=NormalsConfig, description="normals for point-to-plane ICP")
    posegraph: PoseGraphConfig = Field(default_factory=PoseGraphConfig, description="multiway's pose graph")
    kiss: KissConfig = Field(default_factory=KissConfig, description="KISS-ICP")
    event_interval_frames: int = Field(default=10, ge=1, description="emit an iteration event every N frames")
    threads: int = Field(
        default=1, ge=1, le=256, description="CPU threads for Open3D and KISS-ICP (1: bit-for-bit repeatable)"
    )
