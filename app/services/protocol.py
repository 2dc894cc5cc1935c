"""What the service and a job's worker say to each other: the job's spec, and the messages on
the job's pipe. Both sides import this module (pydantic only, no numpy or torch), so a field
added or renamed is one change, checked on both ends.

A worker sends `EventMessage` s while the run goes, then one `DoneMessage`; a Ray worker first
sends a `PidMessage` (its process id, known once its actor has started). The upload reader
(`app.services.worker.reader_loop`) answers each `ReadRequest` with a `ReadOk` or a `ReadFailed`.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter

FinalStatus = Literal["succeeded", "failed", "cancelled"]


class JobSpec(BaseModel):
    """Everything a worker needs to run one job; built by `app.services.jobs.JobService`."""

    model_config = ConfigDict(frozen=True)

    job_id: str
    source: str = Field(description="``sample:NAME`` or the stored upload's path")
    selection: str | None = Field(default=None, description="the upload's own frame selection")
    scene: str | None = Field(
        default=None,
        description="the upload read once (its selection applied): what the job reads, unless it "
        "gives reader options of its own (then the file as uploaded is read again, within the limits)",
    )
    sequence_name: str | None = Field(default=None, description="an upload's name (its stored file is 'sequence')")
    config: str = Field(description="the `RunConfig` as JSON, parsed once the plugins are imported")
    scene_path: str = Field(description="where the worker writes the scene (`app.services.scenes`)")
    tmp_dir: str = Field(description="result files are written here, then renamed to out_dir at once")
    out_dir: str
    log_path: str | None = None
    threads: int = Field(ge=1)
    nice: int = 0
    max_extract_bytes: int
    max_points: int | None = None
    extract_dir: str | None = Field(default=None, description="where a .zip upload is extracted")
    plugins: list[str] = Field(default_factory=list)


class EventMessage(BaseModel):
    """A `strep_core.events` event, as JSON, emitted at ``emitted`` (``time.time()``)."""

    kind: Literal["event"] = "event"
    event_kind: str
    data: str
    emitted: float


class DoneMessage(BaseModel):
    """The job's end: its status, and its metrics and result files when it succeeded."""

    kind: Literal["done"] = "done"
    status: FinalStatus
    error: str | None = None
    metrics: dict[str, Any] | None = None
    files: list[str] = Field(default_factory=list)
    config: dict[str, Any] | None = Field(default=None, description="the resolved `RunConfig` (its config.json)")


class PidMessage(BaseModel):
    """A Ray worker's process id."""

    kind: Literal["pid"] = "pid"
    pid: int


WorkerMessage = Annotated[EventMessage | DoneMessage | PidMessage, Field(discriminator="kind")]
_MESSAGE: TypeAdapter[WorkerMessage] = TypeAdapter(WorkerMessage)


def parse_message(message: Any) -> EventMessage | DoneMessage | PidMessage:
    """A message received from a pipe, checked (a model as sent, or its dict)."""
    return _MESSAGE.validate_python(message)


# ---- the upload reader ----------------------------------------------------------------------


class ReadRequest(BaseModel):
    """Read an upload to validate it, within the service's limits."""

    path: str
    selection: str | None = None
    max_extract_bytes: int
    extract_dir: str | None = None
    max_points: int | None = None
    scene_path: str | None = Field(default=None, description="write what was read here (`app.services.scenes`)")


class ReadOk(BaseModel):
    kind: Literal["ok"] = "ok"
    summary: dict[str, Any] = Field(description="name, frames, dims, points, unit, has_ground_truth")


class ReadFailed(BaseModel):
    kind: Literal["error"] = "error"
    error_class: str = Field(description="the `strep_core.errors` class the reader raised")
    message: str


ReadReply = Annotated[ReadOk | ReadFailed, Field(discriminator="kind")]
_REPLY: TypeAdapter[ReadReply] = TypeAdapter(ReadReply)


def parse_read_reply(reply: Any) -> ReadOk | ReadFailed:
    """A reader's reply received from its pipe, checked."""
    return _REPLY.validate_python(reply)
