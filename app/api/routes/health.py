"""Liveness and the list of registration methods."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool

import strep_core
from app.api.deps import ServiceDep
from app.models import HealthPublic, MethodPublic, MethodsPublic
from strep_core.methods import available

router = APIRouter(tags=["service"])


@router.get("/health", response_model=HealthPublic, summary="Service status")
async def health(service: ServiceDep) -> HealthPublic:
    running, queued = await run_in_threadpool(service.jobs.counts)
    return HealthPublic(
        version=strep_core.__version__,
        jobs_running=running,
        jobs_queued=queued,
        max_concurrent_jobs=service.settings.max_concurrent_jobs,
        methods=list(available()),
        viewer_port=service.viewer.port if service.viewer is not None else None,
        viewer_url=service.viewer.url if service.viewer is not None else None,
    )


@router.get("/methods", response_model=MethodsPublic, summary="Registration methods a job may use")
async def list_methods() -> MethodsPublic:  # the registry in memory: no thread needed
    data = [MethodPublic(name=m.name, description=m.description, learned=m.learned) for m in available().values()]
    return MethodsPublic(data=data, count=len(data))
