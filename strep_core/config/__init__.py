"""One pydantic configuration for a run, nested by concern.

`RunConfig` (here) is the body of a job request, the source of the CLI's options and the
``config.json`` saved beside every result. What a user sets: ``method``, ``start``/``init``,
``frames``, ``seed``, ``device``, ``optim.iterations``, ``profile``, ``data`` (reader options),
``from_model``/``freeze``. The advanced sections live in the package's modules: `sections`
(model, loss, optimiser, data), `classical` (the classical baselines, nested by concern) and
`migrate` (version-1 files' renamed keys). Lengths given as ``None`` are derived from the data
(`strep_core.resolve`) so the same defaults work in pixels and metres.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator

from strep_core.config.classical import (
    ClassicalConfig,
    CorrelativeConfig,
    IcpConfig,
    KissConfig,
    NormalsConfig,
    PoseGraphConfig,
    ScanMatchConfig,
)
from strep_core.config.migrate import RENAMED, migrate
from strep_core.config.sections import (
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
    "CONFIG_VERSION",
    "MAX_POINTS",
    "RENAMED",
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

# The format of a saved config. A file without it is version 1 and is read through the frozen
# table of its renamed keys (`strep_core.config.migrate`); a later rename bumps the version
# and adds one upgrade step, in the same module.
CONFIG_VERSION = 2


def merge(under: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over``'s values over ``under``'s, nested sections merged key by key."""
    out = dict(under)
    for key, value in over.items():
        below = out.get(key)
        out[key] = merge(below, value) if isinstance(below, dict) and isinstance(value, dict) else value
    return out


ProfileName = Literal["auto", "none", "laser-keyframes", "laser-dense", "depth-turning", "depth-handheld", "lidar"]


class RunConfig(Section):
    """Everything one run needs besides its input.

    As given (a request), fields left out and ``auto`` values are decided by the runner's one
    resolve stage (`strep_core.resolve.resolve`): the start, the data's profile, the start's
    overlay, the initial guess, device, threads, batch and the classical lengths. The resolved
    config is what ran and what ``config.json`` holds; loaded again, it re-runs the same values.
    """

    config_version: int = Field(
        default=CONFIG_VERSION, ge=1, le=CONFIG_VERSION, description="format of this config (files without: 1)"
    )
    method: str = Field(default="strep", max_length=64, description="a name from `strep methods`")
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    device: DeviceName = Field(
        default="auto",
        description="torch device of the learned methods: auto = cuda when torch sees one, else cpu "
        "(`strep_core.device.resolve_device`)",
    )
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
    def _upgrade(cls, data: Any) -> Any:
        """An older format's keys read under the current names; the version stamped, so a
        request stored without its defaults (``exclude_unset``) still says its format."""
        if not isinstance(data, dict):
            return data
        version = data.get("config_version")
        if version is None or version == 1:  # version 1: keys renamed by a frozen table
            data = {**migrate(data), "config_version": CONFIG_VERSION}
        # any other value is validated as given (a later version, or nonsense, is refused)
        start, init = data.get("start", "auto"), data.get("init", "auto")
        if start == "scratch" and init in CLASSICAL_INITS:
            raise ValueError(f"start 'scratch' runs no classical step; init {init!r} is one (use pose-graph)")
        return data

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
