"""The sections of the run config, one per concern: model, loss, optimiser, reader options (the
classical baselines' section is `strep_core.config.classical`). `strep_core.config` composes
them into `RunConfig` (and re-exports them: import them from there)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

# A layer width, and the most points any per-frame count may ask for: bounds that keep a
# request from allocating terabytes in a worker (the defaults are far below them).
Width = Annotated[int, Field(ge=1, le=4096)]
MAX_POINTS = 1_000_000


class Section(BaseModel):
    """A section of the run config: unknown fields, NaN and infinity refused, assignments validated."""

    # allow_inf_nan=False: Infinity/NaN (which JSON bodies may carry) are refused, never stored as null
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


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
    loop_radius_fraction: float | None = Field(
        default=0.5,
        gt=0,
        description="also Chamfer to frames farther apart in time whose sensors are closer than this "
        "fraction of the scale in the current estimate; None: temporal neighbours only",
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
    event_interval: int = Field(
        default=5,
        ge=1,
        description="emit an iteration event every N iterations (with several batches: every N sweeps of them)",
    )


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
