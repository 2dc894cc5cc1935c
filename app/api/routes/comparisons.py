"""Comparisons: several methods on one sequence, one job each, side by side."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException

from app.api.deps import ServiceDep
from app.api.routes.jobs import validate_run
from app.models import ComparisonCreate, ComparisonPublic, ErrorPublic, JobPublic
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
def get_comparison(comparison_id: str, service: ServiceDep) -> ComparisonPublic:
    return comparison_public(service, comparison_id)
