"""Jobs: create, list, read, cancel, follow live (SSE) and download result files."""

from __future__ import annotations

import functools
from collections.abc import AsyncIterable
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, HTTPException, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from fastapi.sse import EventSourceResponse, ServerSentEvent

from app.api.deps import JobDep, ServiceDep
from app.models import (
    FILE_MEDIA_TYPES,
    RESULT_FILES,
    ErrorPublic,
    JobCreate,
    JobPublic,
    JobsPublic,
    JobStatus,
    ViewPublic,
)
from app.services import Service
from app.services.live import NothingToShow, ShowFailed
from app.store import FINAL_STATUSES, StoredEvent
from strep_core.config import RunConfig
from strep_core.errors import ConfigError, SequenceError
from strep_core.methods import get as get_method
from strep_core.sequence import FrameSelection

router = APIRouter(prefix="/jobs", tags=["jobs"])

REPLAY_PAGE = 500
EVENT_ID_DIGITS = 18  # event ids are SQLite integers (int64): 18 digits always fit
MAX_EVENT_ID = 10**EVENT_ID_DIGITS - 1  # ?after= has the same bound
EVENT_ID_PATTERN = rf"^\s*[0-9]{{0,{EVENT_ID_DIGITS}}}\s*$"  # what Last-Event-ID accepts (blank: from the start)
IDLE_CHECK_SECONDS = 5.0


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorPublic} for code in codes}


def validate_run(service: Service, sequence_id: str, config: RunConfig) -> None:
    """Check what the body's schema cannot: the sequence, the method, frames, from_model.

    Raises 404 for an unknown sequence, `ConfigError`/`MethodError` (422) for the rest.
    """
    seq = service.sequences.get(sequence_id)
    if seq is None:
        raise HTTPException(404, f"sequence {sequence_id!r} not found")
    get_method(config.method)
    if config.frames:
        try:
            selection = FrameSelection.parse(config.frames)
        except SequenceError as exc:
            raise ConfigError(f"frames: {exc}") from exc
        total = int(seq.get("frames") or 0)
        if total and len(selection.indices(total)) < 2:
            raise ConfigError(f"frames: {str(selection)!r} keeps fewer than 2 of the sequence's {total} frames")
    if config.from_model is not None:
        ref = config.from_model
        source = service.store.get_job(ref[4:]) if ref.startswith("job:") else None
        if source is None:
            raise ConfigError("from_model: give a finished learned job as 'job:<id>' (server paths are not accepted)")
        if "model.pt" not in source["files"]:
            raise ConfigError(f"from_model: job {ref[4:]!r} has no model.pt")
    if config.freeze and config.from_model is None:
        raise ConfigError("freeze needs from_model")


def job_public(service: Service, job_id: str) -> JobPublic:
    row = service.store.get_job(job_id)
    if row is None:
        raise HTTPException(404, f"job {job_id!r} not found")
    return JobPublic.from_row(row)


@router.post(
    "",
    status_code=201,
    response_model=JobPublic,
    responses=_errors(400, 404, 422),
    summary="Queue a job",
    description="The body is a `RunConfig` (method, seed, frames, init, model, loss, optim...) plus `sequence_id`.",
)
def create_job(body: JobCreate, service: ServiceDep) -> JobPublic:
    # the fields given only: the run's resolve stage fills the rest from the data (strep_core.resolve)
    config = RunConfig.model_validate(body.model_dump(exclude={"sequence_id"}, exclude_unset=True))
    validate_run(service, body.sequence_id, config)
    (job_id,), _ = service.jobs.submit(body.sequence_id, [config])
    return job_public(service, job_id)


@router.get("", response_model=JobsPublic, summary="Jobs, newest first")
async def list_jobs(
    service: ServiceDep,
    status: JobStatus | None = None,
    sequence_id: Annotated[str | None, Query(max_length=200)] = None,
    comparison_id: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=2**62)] = 0,
) -> JobsPublic:
    rows, count = await run_in_threadpool(
        functools.partial(
            service.store.list_jobs,
            status=status,
            sequence_id=sequence_id,
            comparison_id=comparison_id,
            limit=limit,
            offset=offset,
        )
    )
    return JobsPublic(data=[JobPublic.from_row(r) for r in rows], count=count)


@router.get("/{job_id}", response_model=JobPublic, responses=_errors(404), summary="One job")
async def get_job(job: JobDep) -> JobPublic:  # the row is read by JobDep, on a thread
    return JobPublic.from_row(job)


@router.delete(
    "/{job_id}",
    response_model=JobPublic,
    status_code=200,
    responses={
        202: {"model": JobPublic, "description": "cancel requested; the worker stops soon"},
        **_errors(404, 409),
    },
    summary="Cancel a job",
    description="A queued job is cancelled at once (200). A running one gets its cancel flag set (202) and is "
    "terminated if it does not stop within `cancel_grace_seconds`. Cancelling a cancelled job is a no-op (200); "
    "other finished jobs answer 409.",
)
def cancel_job(job: JobDep, service: ServiceDep, response: Response) -> JobPublic:
    if job["status"] in FINAL_STATUSES and job["status"] != "cancelled":
        raise HTTPException(409, f"job {job['id']!r} has already finished ({job['status']})")
    after = service.jobs.cancel(job["id"])
    if after is None:
        raise HTTPException(404, f"job {job['id']!r} not found")
    if after["status"] == "running":
        response.status_code = 202
    return JobPublic.from_row(after)


def event_cursor(
    last_event_id: Annotated[
        str,
        Header(
            description="resume after this event id (sent by EventSource on reconnection)",
            # documented, checked below (a 400 that says what an event id is, rather than a 422)
            json_schema_extra={"pattern": EVENT_ID_PATTERN},
        ),
    ] = "",
    after: Annotated[int | None, Query(ge=0, le=MAX_EVENT_ID, description="resume after this event id")] = None,
) -> int:
    cursor = after or 0
    if last_event_id.strip():
        text = last_event_id.strip()
        # ASCII digits only, at most 18 of them, before int(): no digit-limit ValueError, no id past int64
        if not (len(text) <= EVENT_ID_DIGITS and text.isascii() and text.isdigit()):
            raise HTTPException(
                400, f"Last-Event-ID must be a non-negative integer of at most {EVENT_ID_DIGITS} digits (an event id)"
            )
        cursor = max(cursor, int(text))
    return cursor


def _sse(ev: StoredEvent) -> ServerSentEvent:
    return ServerSentEvent(raw_data=ev.data, event=ev.kind, id=str(ev.id))


@router.get(
    "/{job_id}/events",
    response_class=EventSourceResponse,
    responses={
        200: {
            "description": "`text/event-stream`: `id:` the event's number in the job, `event:` its kind "
            "(status, start, stage, iteration, result), `data:` its JSON"
        },
        **_errors(400, 404),
    },
    summary="Follow a job (Server-Sent Events)",
    description="Replays the job's events after `Last-Event-ID` (or `?after=`), then streams live ones; the "
    "stream ends after the job's final status. A client that falls behind receives only the latest iteration "
    "events; the stored log stays complete.",
)
async def job_events(
    job: JobDep, service: ServiceDep, cursor: Annotated[int, Depends(event_cursor)]
) -> AsyncIterable[ServerSentEvent]:
    job_id = job["id"]
    store = service.store
    box = service.broadcaster.subscribe(job_id)  # before the replay, so nothing falls in between
    try:
        sent = cursor
        while True:
            rows = await run_in_threadpool(store.events_after, job_id, sent, REPLAY_PAGE)
            for ev in rows:
                yield _sse(ev)
                sent = ev.id
                if ev.final_status:
                    return
            if len(rows) < REPLAY_PAGE:
                break
        current = await run_in_threadpool(store.get_job, job_id)
        if current is None or (current["status"] in FINAL_STATUSES and sent >= current["last_event_id"]):
            return
        idle = 0.0
        while True:
            batch = await box.get(timeout=1.0)
            if batch is None:  # the service is shutting down
                return
            if not batch:
                idle += 1.0
                if idle < IDLE_CHECK_SECONDS:
                    continue
                # quiet for a while: catch up from the store in case anything was missed
                idle = 0.0
                batch = await run_in_threadpool(store.events_after, job_id, sent, REPLAY_PAGE)
                if not batch:
                    current = await run_in_threadpool(store.get_job, job_id)
                    if current is None or current["status"] in FINAL_STATUSES:
                        return
                    continue
            idle = 0.0
            for ev in batch:
                if ev.id <= sent:
                    continue
                yield _sse(ev)
                sent = ev.id
                if ev.final_status:
                    return
    finally:
        service.broadcaster.unsubscribe(box)


@router.get(
    "/{job_id}/files/{name}",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "the file"},
        **_errors(404, 409),
    },
    summary="Download a result file",
    description="`name` is one of: "
    + ", ".join(RESULT_FILES)
    + " (model.pt for learned methods only; matches.json for icp and multiway).",
)
def job_file(job: JobDep, name: str, service: ServiceDep) -> FileResponse:
    filename = RESULT_FILES.get(name)
    if filename is None:
        raise HTTPException(404, f"no result file named {name!r}; names are: {', '.join(RESULT_FILES)}")
    if job["status"] in ("queued", "running"):
        raise HTTPException(409, f"job {job['id']!r} is {job['status']}; its files appear once it has succeeded")
    path = service.jobs.result_dir(job["id"]) / filename
    if not path.is_file():
        raise HTTPException(404, f"job {job['id']!r} has no {name} ({job['status']})")
    return FileResponse(path, media_type=FILE_MEDIA_TYPES[name], filename=name)


VIEW_DESCRIPTION = (
    "Shows the run in the live 3D viewer (every open viewer tab follows): a finished run is reopened from its "
    "stored events and can be replayed with the viewer's Play and Iteration controls. 409 when the viewer is "
    "disabled, the run has no progress yet or its sequence is gone."
)


def show_in_viewer(service: Service, *, job_id: str | None = None, comparison_id: str | None = None) -> ViewPublic:
    """Ask the viewer feed to show a job (its comparison, if any) or a comparison; HTTP errors."""
    if service.live is None or service.viewer is None:
        raise HTTPException(409, "the 3D viewer is disabled (STREP_VIEWER_ENABLED=false)")
    try:
        shown = service.live.show(job_id=job_id, comparison_id=comparison_id)
    except LookupError as exc:
        raise HTTPException(404, str(exc)) from exc
    except (NothingToShow, ShowFailed) as exc:
        raise HTTPException(409, str(exc)) from exc
    except TimeoutError as exc:
        raise HTTPException(503, "the viewer did not answer in time; try again") from exc
    return ViewPublic(viewer_url=service.viewer.url, group=shown["group"], jobs=shown["jobs"])


@router.post(
    "/{job_id}/view",
    response_model=ViewPublic,
    responses=_errors(404, 409, 503),
    summary="Show a job in the 3D viewer",
    description=VIEW_DESCRIPTION + " A job of a comparison is shown with the other methods of its comparison.",
)
def view_job(job: JobDep, service: ServiceDep) -> ViewPublic:
    return show_in_viewer(service, job_id=job["id"])
