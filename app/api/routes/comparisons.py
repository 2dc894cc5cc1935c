"""Comparisons: several methods on one sequence, one job each, side by side."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from app.api.deps import ServiceDep
from app.api.routes.jobs import VIEW_DESCRIPTION, show_in_viewer, validate_run
from app.models import COMPARISON_FILES, ComparisonCreate, ComparisonPublic, ErrorPublic, JobPublic, ViewPublic
from app.services import Service
from strep_core.errors import ConfigError

router = APIRouter(prefix="/comparisons", tags=["comparisons"])

_OUTCOME_ORDER = ("failed", "interrupted", "cancelled", "succeeded")


def comparison_status(statuses: list[str]) -> str:
    """``running`` while any job is queued or running (``queued`` if all are), else the worst outcome."""
    if statuses and all(s == "queued" for s in statuses):
        return "queued"
    if any(s in ("queued", "running") for s in statuses):
        return "running"
    for outcome in _OUTCOME_ORDER:
        if outcome in statuses:
            return outcome
    return "succeeded"


def comparison_public(service: Service, comparison_id: str) -> ComparisonPublic:
    comparison = service.store.get_comparison(comparison_id)
    if comparison is None:
        raise HTTPException(404, f"comparison {comparison_id!r} not found")
    rows, _ = service.store.list_jobs(comparison_id=comparison_id, limit=1000, newest_first=False)
    jobs = [JobPublic.from_row(r) for r in rows]
    return ComparisonPublic(
        id=comparison["id"],
        sequence_id=comparison["sequence_id"],
        methods=comparison["methods"],
        created_at=comparison["created_at"],
        status=comparison_status([j.status for j in jobs]),  # type: ignore[arg-type]
        jobs=jobs,
        files=[name for name in COMPARISON_FILES if service.recordings.path(comparison_id).is_file()],
    )


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorPublic} for code in codes}


@router.post(
    "",
    status_code=201,
    response_model=ComparisonPublic,
    responses=_errors(400, 404, 422),
    summary="Compare methods",
    description="Queues one job per method (default strep and strep-nolink) with the shared `config`; "
    "the jobs share a `comparison_id`.",
)
def create_comparison(body: ComparisonCreate, service: ServiceDep) -> ComparisonPublic:
    if "method" in body.config.model_fields_set:
        raise ConfigError("config.method: give the methods in 'methods', not in config")
    configs = [body.config.model_copy(update={"method": m}) for m in body.methods]
    for cfg in configs:
        validate_run(service, body.sequence_id, cfg)
    _, comparison_id = service.jobs.submit(body.sequence_id, configs, comparison_methods=list(body.methods))
    assert comparison_id is not None
    return comparison_public(service, comparison_id)


@router.get("/{comparison_id}", response_model=ComparisonPublic, responses=_errors(404), summary="One comparison")
async def get_comparison(comparison_id: str, service: ServiceDep) -> ComparisonPublic:
    return await run_in_threadpool(comparison_public, service, comparison_id)


@router.get(
    "/{comparison_id}/files/{name}",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "the file"},
        **_errors(404, 409),
    },
    summary="Download a comparison's file",
    description="`name`: recording.rrd, one Rerun recording with every method of the comparison side by side "
    "(open it with `rerun recording.rrd`). It is written shortly after the comparison's last job finished: "
    "409 (with `Retry-After`) until then; 404 when none of its jobs reported progress.",
)
def comparison_file(comparison_id: str, name: str, service: ServiceDep) -> FileResponse:
    comparison = comparison_public(service, comparison_id)
    filename = COMPARISON_FILES.get(name)
    if filename is None:
        raise HTTPException(404, f"no comparison file named {name!r}; names are: {', '.join(COMPARISON_FILES)}")
    if comparison.status in ("queued", "running"):
        raise HTTPException(
            409,
            f"comparison {comparison_id!r} is {comparison.status}; its recording is written once all its jobs finish",
        )
    state, reason = service.recordings.state(comparison_id)
    if state == "failed":
        raise HTTPException(404, f"comparison {comparison_id!r} has no {name}: {reason}")
    if state != "ready":
        service.recordings.ensure(comparison_id)
        raise HTTPException(
            409,
            f"the {name} of comparison {comparison_id!r} is being written; retry shortly",
            headers={"Retry-After": "1"},
        )
    path = service.recordings.path(comparison_id)
    return FileResponse(path, media_type="application/octet-stream", filename=f"{comparison_id}-{filename}")


@router.post(
    "/{comparison_id}/view",
    response_model=ViewPublic,
    responses=_errors(404, 409, 503),
    summary="Show a comparison in the 3D viewer",
    description=VIEW_DESCRIPTION,
)
def view_comparison(comparison_id: str, service: ServiceDep) -> ViewPublic:
    if service.store.get_comparison(comparison_id) is None:
        raise HTTPException(404, f"comparison {comparison_id!r} not found")
    return show_in_viewer(service, comparison_id=comparison_id)
