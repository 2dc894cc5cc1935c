"""Request and response schemas of the REST API (``XCreate`` in, ``XPublic`` out)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from strep_core.config import RunConfig
from strep_core.result import OUTPUT_FILES

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]

RESULT_FILES: dict[str, str] = {
    # public name -> file name inside the job's result folder (an allow-list: never a path join of
    # input): what a run writes (strep_core.result.OUTPUT_FILES) and the job's recording
    **{name: name for name in OUTPUT_FILES},
    "recording.rrd": "recording.rrd",
}
_MEDIA_BY_SUFFIX = {".tum": "text/plain; charset=utf-8", ".json": "application/json"}
FILE_MEDIA_TYPES: dict[str, str] = {
    name: _MEDIA_BY_SUFFIX.get(name[name.rindex(".") :], "application/octet-stream") for name in RESULT_FILES
}


class ErrorPublic(BaseModel):
    """Every error answer: a readable message, and the field errors of a 422 when there are some."""

    detail: str = Field(description="what is wrong, in one line")
    errors: list[dict[str, Any]] | None = Field(default=None, description="per-field problems (validation errors)")


class HealthPublic(BaseModel):
    status: Literal["ok"] = "ok"
    version: str
    jobs_running: int
    jobs_queued: int
    max_concurrent_jobs: int
    methods: list[str]
    viewer_port: int | None = Field(default=None, description="port of the live 3D viewer; null when disabled")
    viewer_url: str | None = Field(default=None, description="address of the live 3D viewer; null when disabled")


class MethodPublic(BaseModel):
    name: str
    description: str
    learned: bool


class MethodsPublic(BaseModel):
    data: list[MethodPublic]
    count: int


# ---- sequences -----------------------------------------------------------------------------


class SequencePublic(BaseModel):
    """An input sequence: uploaded (``id`` like ``seq_...``) or bundled (``sample:NAME``)."""

    id: str
    name: str
    source: Literal["upload", "sample"]
    frames: int = Field(description="frames after the sequence's frame selection")
    dims: int = Field(description="2 or 3")
    points: int = Field(description="points over all frames")
    unit: str | None = Field(default=None, description="'px' (map pixels) or 'm'")
    has_ground_truth: bool | None = Field(default=None, description="None when not known without reading it")
    format: str | None = Field(default=None, description="format of the uploaded file (npz, zip, carmen...)")
    filename: str | None = Field(default=None, description="name of the uploaded file")
    selection: str | None = Field(default=None, description="frame selection applied at upload (start:stop[:step])")
    size_bytes: int | None = None
    description: str | None = None
    created_at: datetime | None = None


class SequencesPublic(BaseModel):
    data: list[SequencePublic]
    count: int


# ---- jobs ----------------------------------------------------------------------------------


class JobCreate(RunConfig):
    """A job: the sequence to register and the run configuration (`RunConfig`, flat)."""

    sequence_id: str = Field(min_length=1, max_length=200, description="id of an uploaded or bundled sequence")


class ComparisonCreate(BaseModel):
    """Several methods on one sequence with one shared configuration: one job per method."""

    model_config = ConfigDict(extra="forbid")

    sequence_id: str = Field(min_length=1, max_length=200)
    methods: list[Annotated[str, Field(min_length=1, max_length=64)]] = Field(
        default_factory=lambda: ["strep", "strep-nolink"], min_length=1, max_length=16, description="distinct names"
    )
    config: RunConfig = Field(default_factory=RunConfig, description="shared run configuration (its method is ignored)")

    @field_validator("methods")
    @classmethod
    def _distinct(cls, methods: list[str]) -> list[str]:
        if len(set(methods)) != len(methods):
            raise ValueError("methods must be distinct")
        return methods


class JobPublic(BaseModel):
    id: str
    status: JobStatus
    method: str
    sequence_id: str
    comparison_id: str | None = None
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    error: str | None = Field(default=None, description="why it failed, was cancelled or interrupted")
    metrics: dict[str, Any] | None = Field(default=None, description="metrics.json, once succeeded")
    files: list[str] = Field(default_factory=list, description="names for GET /api/jobs/{id}/files/{name}")
    config: dict[str, Any] = Field(
        description="the RunConfig as requested (the fields given) until the job succeeds, then as resolved by "
        "the run (its config.json: every value that ran); kept as stored, so older jobs still read back"
    )
    cancel_requested: bool = False
    exit_code: int | None = Field(default=None, description="the worker process's exit code (negative: signal)")
    last_event_id: int = Field(description="id of the job's latest event (SSE ids run 1..last_event_id)")

    @classmethod
    def from_row(cls, row: dict[str, Any]) -> JobPublic:
        return cls.model_validate({k: v for k, v in row.items() if k in cls.model_fields})


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int = Field(description="jobs matching the filters (all pages)")


class ComparisonPublic(BaseModel):
    id: str
    sequence_id: str
    methods: list[str]
    created_at: datetime
    status: JobStatus = Field(description="running while any job is queued or running; else the worst outcome")
    jobs: list[JobPublic]
    files: list[str] = Field(
        default_factory=list,
        description="names for GET /api/comparisons/{id}/files/{name}: recording.rrd (all methods side by side) "
        "once written, shortly after the last job finished",
    )


COMPARISON_FILES: dict[str, str] = {"recording.rrd": "recording.rrd"}


class ViewPublic(BaseModel):
    """What the live 3D viewer shows after a ``view`` request."""

    viewer_url: str = Field(description="address of the 3D viewer")
    group: str = Field(description="the run shown: the comparison id, or the job id of a job alone")
    jobs: list[str] = Field(description="the jobs drawn side by side")
