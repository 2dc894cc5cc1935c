"""One pydantic configuration for a run, nested by concern.

`RunConfig` is the body of a job request, the source of the CLI's options and the
``config.json`` saved beside every result. Lengths given as ``None`` are derived from the
data (see `strep_core.sequence.Sequence.scale`) so the same defaults work in pixels and metres.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationError, model_validator

from strep_core._config_classical import (
    ClassicalConfig,
    CorrelativeConfig,
    IcpConfig,
    KissConfig,
    NormalsConfig,
    PoseGraphConfig,
    ScanMatchConfig,
)
from strep_core._config_migrate import RENAMED, migrate
from strep_core._config_sections import (
    MAX_POINTS,
    DataConfig,
    LossConfig,
    ModelConfig,
    OptimConfig,
    Section,
    Width,
)
from strep_core.errors import ConfigError

__all__ = [
    "CLASSICAL_INITS",
    "MAX_POINTS",
    "RENAMED",
    "SCRATCH_PROFILE",
    "ClassicalConfig",
    "CorrelativeConfig",
    "DataConfig",
    "DeviceName",
    "IcpConfig",
    "InitName",
    "KissConfig",
    "LossConfig",
    "ModelConfig",
    "NormalsConfig",
    "OptimConfig",
    "PoseGraphConfig",
    "ProfileName",
    "RunConfig",
    "ScanMatchConfig",
    "Section",
    "StartName",
    "Width",
    "format_validation_error",
]

InitName = Literal["auto", "identity", "odometry", "ground_truth", "icp", "multiway", "kiss", "fpfh"]
StartName = Literal["auto", "scratch", "pose-graph"]
DeviceName = Literal["cpu", "cuda", "auto"]
# initial guesses that run a classical method first (a from-scratch start runs none)
CLASSICAL_INITS = frozenset({"icp", "multiway", "kiss", "fpfh"})


# The learned methods' settings when they start from scratch (no classical step), applied to
# every field a request leaves out; measured in docs/design/from-scratch.md. The defaults of
# the sections are those of the pose-graph warm start.
SCRATCH_PROFILE: dict[str, dict[str, Any]] = {
    "model": {"link_init": 1.0},
    # temporal pairs (Huber) form the chain; from halfway, loop pairs (truncated, weighted by
    # window / span) close it: v1_pose0 1.75 -> 0.47 px (docs/design/from-scratch.md)
    "loss": {
        "robust": "huber",
        "loop_radius_fraction": 0.5,
        "loop_after": 0.5,
        "loop_robust": "truncated",
        "loop_weight": "span",
    },
    "optim": {"lr_latent": 1e-2, "iterations": 1000},
}


def merge(under: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over``'s values over ``under``'s, nested sections merged key by key."""
    out = dict(under)
    for key, value in over.items():
        below = out.get(key)
        out[key] = merge(below, value) if isinstance(below, dict) and isinstance(value, dict) else value
    return out


def _overlay(given: Any, profile: dict[str, Any]) -> dict[str, Any]:
    """``profile`` under the values of ``given`` (a dict or a section model: its set fields,
    nested sections included)."""
    if isinstance(given, BaseModel):
        given = given.model_dump(exclude_unset=True)
    return merge(profile, given or {})


def _under(given: Any, section: type[BaseModel], profile: dict[str, Any]) -> Any:
    """``profile``'s values under ``given``'s, as a section whose *set* fields are only ``given``'s:
    the data's profile (`strep_core.profiles.resolve`) may still replace the others."""
    try:
        out = section.model_validate(_overlay(given, profile))
    except ValidationError:
        return _overlay(given, profile)  # reported with its field path by RunConfig's own validation
    given_names = given.model_fields_set if isinstance(given, BaseModel) else set(given or {})
    out.__pydantic_fields_set__ = set(given_names)
    return out


ProfileName = Literal["auto", "none", "laser-keyframes", "laser-dense", "depth-turning", "depth-handheld", "lidar"]


class RunConfig(Section):
    """Everything one run needs besides its input.

    ``start`` is resolved when the config is built: ``auto`` becomes ``scratch`` when ``init``
    is ``identity`` and ``pose-graph`` otherwise; ``scratch`` fills the fields left out with
    `SCRATCH_PROFILE` (and ``init`` ``auto`` with ``identity``). A saved config holds every
    field, so it reproduces its run whatever the profile becomes.
    """

    method: str = Field(default="strep", max_length=64, description="a name from `strep methods`")
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    device: DeviceName = "cpu"
    threads: int | None = Field(default=None, ge=1, le=256, description="torch CPU threads; None: all cores")
    init: InitName = Field(
        default="auto",
        description="initial guess: auto = odometry if the data has it, else identity, "
        "and for learned methods a pose-graph (multiway) warm start from that",
    )
    start: StartName = Field(
        default="auto",
        description="learned methods: scratch = from identity with no classical step, the paper's setting "
        "(its own loss and optimiser settings for the fields not given); pose-graph = refine a classical "
        "warm start (init auto: the multiway pose graph; with init identity: the same settings from identity); "
        "auto = scratch if init is identity, else pose-graph",
    )
    frames: str | None = Field(default=None, max_length=64, description="frame selection start:stop[:step]")
    data: DataConfig = Field(default_factory=DataConfig, description="reader options")
    profile: ProfileName = Field(
        default="auto",
        description="settings chosen from the data (`strep_core.profiles`): auto = a probe of a few frame pairs "
        "picks one; a name applies it to the fields not given; none = the defaults",
    )
    profile_reason: str | None = Field(
        default=None, max_length=500, description="set by the run: why this profile (the probe's measures)"
    )
    classical: ClassicalConfig = Field(default_factory=ClassicalConfig)
    model: ModelConfig = Field(default_factory=ModelConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    optim: OptimConfig = Field(default_factory=OptimConfig)
    from_model: str | None = Field(default=None, max_length=300, description="path of a saved model to start from")
    freeze: bool = Field(default=False, description="with from_model: re-optimise only the latents")

    @model_validator(mode="before")
    @classmethod
    def _resolve_start(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        data = migrate(data)  # old keys first: the profiles below see the new names only
        start, init = data.get("start", "auto"), data.get("init", "auto")
        if start == "auto":
            start = "scratch" if init == "identity" else "pose-graph"
        if start == "scratch":
            if init in CLASSICAL_INITS:
                raise ValueError(f"start 'scratch' runs no classical step; init {init!r} is one (use pose-graph)")
            data = {
                **data,
                **{
                    name: _under(data.get(name), cls.model_fields[name].annotation, values)
                    for name, values in SCRATCH_PROFILE.items()
                },
                "init": "identity" if init == "auto" else init,
            }
        # start "pose-graph" with init "identity": the warm-start settings from identity (the
        # benchmark's bunny[identity] rows); their saved config.json must load again
        return {**data, "start": start}

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
