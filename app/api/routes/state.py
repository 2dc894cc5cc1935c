"""What the page draws: typed run-state snapshots of jobs (reduced here, by
`strep_core.runstate`) and the starts a comparison may use, with their default budgets.

The page interprets no events: ``GET /api/jobs/{id}/state`` follows a job's event stream
(`app.api.routes.jobs.job_events`), folds it with `strep_core.runstate.apply` and sends a
`JobStatePublic` after each batch; the page replaces its view of the job with it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterable
from typing import Any

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import BaseModel, Field

from app.api.deps import JobDep, ServiceDep
from app.api.routes.jobs import job_events
from app.models import ComparisonCreate, JobStatus
from strep_core.config import RunConfig
from strep_core.events import progress_events
from strep_core.methods import available
from strep_core.runstate import History, RunState, apply
from strep_core.runview import RunView, run_view

router = APIRouter(tags=["page"])

HISTORY = 240  # curve points kept per job (the history halves its step when full)


class JobStatePublic(BaseModel):
    """One job as the page shows it: the store's record and the run's view."""

    id: str
    status: JobStatus
    error: str | None = None
    sequence_id: str
    comparison_id: str | None = None
    files: list[str] = Field(default_factory=list, description="names for GET /api/jobs/{id}/files/{name}")
    run: RunView


class StartPublic(BaseModel):
    name: str = Field(description="the value of RunConfig.start")
    label: str
    description: str
    iterations: int = Field(description="the learned methods' default iterations from this start")


class StartsPublic(BaseModel):
    data: list[StartPublic]
    default: str


class PresetPublic(BaseModel):
    """The comparison the page offers first: the link decides the outcome on this sample
    (0.45 px against 134 px from scratch, docs/design/from-scratch.md)."""

    sequence_id: str
    methods: list[str]
    start: str


# the starts the page offers, in its order (RunConfig.start also takes "auto": decided by init)
STARTS = {
    "scratch": ("from scratch", "from the identity, with no classical step: the paper's setting"),
    "pose-graph": ("from the pose graph", "ICP and loop closures first, then the learned loop refines them"),
}


@router.get("/starts", response_model=StartsPublic, summary="How a comparison's learned methods may start")
async def list_starts() -> StartsPublic:
    data = [
        StartPublic(name=name, label=label, description=text, iterations=default_iterations(name))
        for name, (label, text) in STARTS.items()
    ]
    return StartsPublic(data=data, default="scratch")


@router.get("/preset", response_model=PresetPublic, summary="The comparison the page offers first")
async def preset() -> PresetPublic:
    methods = ComparisonCreate.model_fields["methods"].get_default(call_default_factory=True)
    return PresetPublic(sequence_id="sample:sim2d", methods=methods, start="scratch")


def default_iterations(start: str) -> int:
    """The iterations a learned run from ``start`` gets when a request names none: the start's
    overlay over the defaults (`strep_core.profiles.START_OVERLAYS`, applied by the resolve stage)."""
    from strep_core.profiles import START_OVERLAYS

    default = RunConfig.build(method="strep").optim.iterations
    return int(START_OVERLAYS.get(start, {}).get("optim", {}).get("iterations", default))


class JobState:
    """A job's run state and store record, folded from its stored events."""

    def __init__(self, job: dict[str, Any]) -> None:
        method = available().get(job["method"])
        self.learned = bool(method and method.learned)
        self.job = job
        self.state = RunState(keep_poses=False, history=History(HISTORY))
        self.state.method = job["method"]
        self.status: str = job["status"]
        self.error: str | None = None

    def apply(self, kind: str, data: str) -> None:
        if kind == "status":
            record = json.loads(data)
            self.status = record.get("status", self.status)
            self.error = record.get("error") or self.error
            return
        for event in progress_events([{"kind": kind, **json.loads(data)}]):
            apply(self.state, event)

    def public(self) -> JobStatePublic:
        run = run_view(self.state, learned=self.learned, status=self.status)
        return JobStatePublic(
            id=self.job["id"],
            status=self.status,  # type: ignore[arg-type]
            error=self.error,
            sequence_id=self.job["sequence_id"],
            comparison_id=self.job.get("comparison_id"),
            files=self.job["files"] if self.status == "succeeded" else [],
            run=run,
        )


@router.get(
    "/jobs/{job_id}/state",
    response_class=EventSourceResponse,
    responses={200: {"description": "`text/event-stream` of `JobStatePublic` (`event: state`), ends when it does"}},
    summary="Follow a job as the page draws it (Server-Sent Events of typed snapshots)",
    description="Each message is the whole `JobStatePublic` after a batch of the job's events: the first one "
    "holds everything so far (a reloaded page is whole at once), the last one the final status and files.",
)
async def job_state(job: JobDep, service: ServiceDep) -> AsyncIterable[ServerSentEvent]:
    folded = JobState(job)
    queue: asyncio.Queue[ServerSentEvent | None] = asyncio.Queue()

    async def pump() -> None:
        try:
            async for sse in job_events(job, service, 0):
                await queue.put(sse)
        finally:
            await queue.put(None)

    task = asyncio.create_task(pump())
    try:
        ended = False
        while not ended:
            batch = [await queue.get()]
            while not queue.empty():
                batch.append(queue.get_nowait())
            for sse in batch:
                if sse is None:
                    ended = True
                elif sse.event:
                    folded.apply(sse.event, str(sse.raw_data))
            if folded.status in ("succeeded", "failed", "cancelled", "interrupted"):
                folded.job = await run_in_threadpool(service.store.get_job, job["id"]) or folded.job
            yield ServerSentEvent(raw_data=folded.public().model_dump_json(), event="state")
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
