"""One pydantic configuration for a run, nested by concern.

`RunConfig` is the body of a job request, the source of the CLI's options and the
``config.json`` saved beside every result. Lengths given as ``None`` are derived from the
data (see `strep_core.sequence.Sequence.scale`) so the same defaults work in pixels and metres.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from strep_core.errors import ConfigError

InitName = Literal["auto", "identity", "odometry", "ground_truth", "icp", "multiway", "kiss"]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


# ---- classical baselines -------------------------------------------------------------------


class ClassicalConfig(_Section):
    """Settings of the classical baselines (`icp`, `multiway`, `kiss`)."""

    max_correspondence: float | None = Field(
        default=None, gt=0, description="ICP correspondence distance (sequence unit); None: from data"
    )
    voxel: float | None = Field(
        default=None, gt=0, description="voxel size for downsampling (sequence unit); None: from data"
    )
    icp_iterations: int = Field(default=50, ge=1, le=1000)
    loop_radius: float | None = Field(
        default=None, gt=0, description="multiway: loop-closure search radius; None: from data"
    )
    loop_min_fitness: float = Field(default=0.6, ge=0, le=1)
    loop_max_candidates: int = Field(default=8, ge=0, le=100, description="loop edges tried per frame")
    kiss_voxel: float | None = Field(default=None, gt=0, description="KISS-ICP voxel size; None: from data")


# ---- learned methods (strep, strep-nolink, deepmapping) ------------------------------------


class ModelConfig(_Section):
    """Network shapes. Defaults are the paper's."""

    latent_dim: int | None = Field(default=None, ge=1, le=512, description="None: 16 in 2D, 24 in 3D")
    point_layers: list[int] = Field(default=[64, 256, 1024], min_length=1)
    head_layers: list[int] = Field(default=[512, 128])
    occupancy_layers: list[int] = Field(default=[64, 256, 512, 256, 128], min_length=1)


class LossConfig(_Section):
    """Loss terms and their weights."""

    chamfer_weight: float = Field(default=1.0, ge=0)
    occupancy_weight: float = Field(default=1.0, ge=0)
    window: int = Field(default=2, ge=1, le=64, description="Chamfer to neighbours within +-window frames")
    free_samples: int = Field(default=1, ge=0, le=64, description="free-space samples per ray")


class OptimConfig(_Section):
    """The per-sequence optimisation."""

    iterations: int = Field(default=300, ge=0, le=100_000)
    lr_network: float = Field(default=1e-3, gt=0, le=1)
    lr_latent: float = Field(default=1e-4, gt=0, le=1)
    batch_frames: int | None = Field(default=None, ge=2, description="frames per batch; None: all")
    points_per_frame: int | None = Field(default=None, ge=8, description="points per frame per step; None: auto")
    event_interval: int = Field(default=5, ge=1, description="emit an iteration event every N iterations")


class RunConfig(_Section):
    """Everything one run needs besides its input."""

    method: str = Field(default="strep", description="a name from `strep methods`")
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    threads: int | None = Field(default=None, ge=1, le=256, description="torch CPU threads; None: all cores")
    init: InitName = Field(
        default="auto",
        description="initial guess: auto = odometry if the data has it, else identity, "
        "and for learned methods an ICP warm start from that",
    )
    frames: str | None = Field(default=None, description="frame selection start:stop[:step]")
    classical: ClassicalConfig = Field(default_factory=ClassicalConfig)
    model: ModelConfig = Field(default_factory=ModelConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    optim: OptimConfig = Field(default_factory=OptimConfig)
    from_model: str | None = Field(default=None, description="path of a saved model to start from")
    freeze: bool = Field(default=False, description="with from_model: re-optimise only the latents")

    def to_json(self) -> str:
        return self.model_dump_json(indent=2)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json() + "\n")

    @classmethod
    def load(cls, path: str | Path) -> RunConfig:
        try:
            return cls.model_validate(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError, ValidationError) as exc:
            raise ConfigError(f"cannot read run config {path}: {exc}") from exc

    @classmethod
    def build(cls, **values: object) -> RunConfig:
        """Validate values into a config, raising `ConfigError` with a readable message."""
        try:
            return cls.model_validate(values)
        except ValidationError as exc:
            raise ConfigError(format_validation_error(exc)) from exc


def format_validation_error(exc: ValidationError) -> str:
    """One line per problem: ``field.path: message``."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "config"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)
