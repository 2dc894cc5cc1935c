"""The service's settings: one `BaseSettings` read from ``STREP_*`` environment variables.

These are settings of the *service* (where data lives, how many jobs run at once, limits,
security). The settings of a *run* are `strep_core.config.RunConfig`, the body of a job.
"""

from __future__ import annotations

import importlib.util
import ipaddress
import json
import os
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MiB = 1024**2
GiB = 1024**3

LOOPBACK_NAMES = {"localhost", "localhost.localdomain", "ip6-localhost"}
RAY_MISSING = "STREP_EXECUTOR=ray needs Ray, an optional extra: pip install 'strep-studio[ray]'"


def is_loopback(host: str) -> bool:
    """True when ``host`` only accepts connections from this machine (127.0.0.0/8, ::1, localhost)."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _split_list(value: Any) -> Any:
    """Accept a JSON list or a comma-separated string for list settings given in the environment."""
    if isinstance(value, str):
        text = value.strip()
        if not text:
            return []
        if text.startswith("["):
            return json.loads(text)
        return [part.strip() for part in text.split(",") if part.strip()]
    return value


class ViewerSettings(BaseModel):
    """The live 3D viewer's settings (`app.viewer.ViewerServer`), the ``viewer`` section of `Settings`:
    ``STREP_VIEWER__MAX_RATE_HZ=5`` or ``STREP_VIEWER='{"max_rate_hz": 5}'``. Its port stays
    ``viewer_port`` (``STREP_VIEWER_PORT``), beside the service's own host and port."""

    model_config = ConfigDict(extra="forbid")

    max_points_per_job: int = Field(default=30_000, ge=1, description="points drawn per job (frames evenly strided)")
    max_rate_hz: float = Field(default=10.0, gt=0, description="pushes per second per job, at most")
    history_limit: int = Field(default=256, ge=2, description="snapshots kept per job for replay (then decimated 2:1)")
    max_pose_markers: int = Field(default=64, ge=1, description="pose axes drawn per job")
    frame_nodes_max: int = Field(
        default=512,
        ge=0,
        description="up to this many frames, each frame is its own cloud moved by its pose (a push sends K "
        "poses); above, one fused cloud is re-sent per push",
    )
    max_jobs: int = Field(default=32, ge=1, description="jobs kept; beyond, the oldest finished ones are removed")
    chart_interval: float = Field(
        default=0.5, ge=0, description="seconds between chart updates of a job (its text follows every push)"
    )


class Settings(BaseSettings):
    """Settings of the STREP Studio service (environment prefix ``STREP_``; nested sections with
    ``__``, e.g. ``STREP_VIEWER__MAX_JOBS``)."""

    model_config = SettingsConfigDict(
        env_prefix="STREP_", env_nested_delimiter="__", extra="ignore", validate_default=True
    )

    data_dir: Path = Field(default=Path("strep-data"), description="SQLite store, uploads and job results")
    host: str = Field(default="127.0.0.1", description="bind address; a non-loopback one needs api_token")
    port: int = Field(default=8000, ge=0, le=65535, description="HTTP port")
    max_concurrent_jobs: int = Field(default=2, ge=1, le=256, description="jobs optimising at once; more queue")
    max_upload_bytes: int = Field(default=512 * MiB, ge=1, description="largest accepted upload (bytes)")
    max_inflated_bytes: int = Field(
        default=2 * GiB,
        ge=1,
        description="most one read of a sequence may inflate to, all containers and compressed streams "
        "together (.zip, .npz, gzip, .tar; bytes), counted while inflating",
    )
    max_pending_uploads: int = Field(
        default=8,
        ge=1,
        le=1024,
        description="uploads being received, waiting for the reader or read at once; more get 429 at once",
    )
    max_points: int = Field(
        default=20_000_000, ge=1, description="most points one sequence may hold (counted while it is read)"
    )
    max_body_bytes: int = Field(
        default=1 * MiB, ge=1024, description="largest accepted request body other than an upload (bytes)"
    )
    allowed_hosts: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="without api_token: Host names accepted besides localhost, 127.0.0.1 and ::1 "
        "(comma-separated or JSON); other Host headers get 421 (DNS rebinding)",
    )
    api_token: SecretStr | None = Field(
        default=None, description="bearer token required on every /api call when set (mandatory off loopback)"
    )
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="origins allowed by CORS (comma-separated or JSON); none by default"
    )
    viewer_enabled: bool = Field(
        default=True, description="serve the live 3D viewer (viser) beside the API, on the same host"
    )
    viewer_port: int = Field(
        default=8080,
        ge=0,
        le=65535,
        description="port of the 3D viewer; when taken, the next free one (see /api/health); 0: any free port",
    )
    viewer: ViewerSettings = Field(default_factory=ViewerSettings, description="the live 3D viewer")
    cancel_grace_seconds: float = Field(
        default=5.0, gt=0, le=600, description="after a cancel, a worker still running this long is terminated"
    )
    worker_threads: int | None = Field(
        default=None,
        ge=1,
        le=256,
        description="CPU threads per job when its config leaves `threads` unset; None: cores / max_concurrent_jobs",
    )
    job_memory_mib: int | None = Field(
        default=4096,
        ge=64,
        le=2**24,
        description="memory a job's worker may hold (resident, MiB); past it the job fails with that reason and "
        "the service and the other jobs run on; None: no budget",
    )
    worker_nice: int = Field(
        default=10,
        ge=0,
        le=19,
        description="niceness added to worker processes, so the API stays responsive while jobs optimise",
    )
    read_timeout_seconds: float = Field(
        default=300.0, gt=0, description="longest time reading an upload may take before it is refused"
    )
    plugins: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="modules imported by the service and by every worker, e.g. to register extra methods",
    )

    executor: Literal["local", "ray"] = Field(
        default="local",
        description="where jobs run: 'local' worker processes, or 'ray' (one Ray actor per job; needs the ray extra)",
    )
    ray_address: str = Field(
        default="local",
        description="with executor=ray: 'local' starts a Ray runtime in the service, 'auto' joins the running "
        "cluster (RAY_ADDRESS or `ray start`), anything else is a cluster address (e.g. 10.0.0.5:6379)",
    )
    ray_num_cpus: int | None = Field(
        default=None, ge=1, le=4096, description="CPUs of the local Ray runtime (ray_address=local); None: all cores"
    )

    @field_validator("cors_origins", "plugins", "allowed_hosts", mode="before")
    @classmethod
    def _lists(cls, value: Any) -> Any:
        return _split_list(value)

    @field_validator("api_token", mode="before")
    @classmethod
    def _empty_token_is_none(cls, value: Any) -> Any:
        return None if isinstance(value, str) and not value.strip() else value

    @model_validator(mode="after")
    def _ray_installed(self) -> Settings:
        if self.executor == "ray" and importlib.util.find_spec("ray") is None:
            raise ValueError(RAY_MISSING)
        return self

    @property
    def db_path(self) -> Path:
        return self.data_dir / "strep.db"

    @property
    def uploads_dir(self) -> Path:
        return self.data_dir / "uploads"

    @property
    def results_dir(self) -> Path:
        return self.data_dir / "results"

    @property
    def logs_dir(self) -> Path:
        return self.data_dir / "logs"

    def threads_per_job(self) -> int:
        """Torch/Open3D threads for a job whose config does not say: the cores shared by the job slots."""
        if self.worker_threads is not None:
            return self.worker_threads
        return max(1, (os.cpu_count() or 1) // self.max_concurrent_jobs)

    def check_secure(self) -> None:
        """Raise `InsecureSettings` when bound off loopback without a token."""
        if not is_loopback(self.host) and self.api_token is None:
            raise InsecureSettings(
                f"refusing to listen on {self.host}: set STREP_API_TOKEN to serve beyond this machine "
                "(clients then send 'Authorization: Bearer <token>')"
            )


class InsecureSettings(RuntimeError):
    """The settings would expose the service without authentication."""


@lru_cache
def get_settings() -> Settings:
    """The settings from the environment (cached)."""
    return Settings()
