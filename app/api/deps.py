"""Dependencies shared by the routes (``Annotated`` aliases).

They are ``async``: FastAPI runs a plain ``def`` dependency on a thread of its pool, and each
such hop waits for a thread to be scheduled, which is what a request's latency is made of on
a busy machine (issue 17 item 13). Only the store read of `get_job` goes to a thread; the rest
is a few attribute reads and one comparison."""

from __future__ import annotations

import hmac
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.core.config import Settings
from app.services import Service

bearer = HTTPBearer(auto_error=False, description="STREP_API_TOKEN, when the service has one")


async def get_service(request: Request) -> Service:
    service = getattr(request.app.state, "service", None)
    if service is None:
        raise HTTPException(503, "the service is starting or stopping")
    return service


ServiceDep = Annotated[Service, Depends(get_service)]


async def get_settings(service: ServiceDep) -> Settings:
    return service.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


async def require_token(
    service: ServiceDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """With ``STREP_API_TOKEN`` set, every API call needs ``Authorization: Bearer <token>``."""
    token = service.settings.api_token
    if token is None:
        return
    given = credentials.credentials if credentials is not None else ""
    if not hmac.compare_digest(given.encode(), token.get_secret_value().encode()):
        raise HTTPException(401, "missing or invalid bearer token", headers={"WWW-Authenticate": "Bearer"})


async def get_job(job_id: str, service: ServiceDep) -> dict[str, Any]:
    job = await run_in_threadpool(service.store.get_job, job_id)  # SQLite stays off the event loop
    if job is None:
        raise HTTPException(404, f"job {job_id!r} not found")
    return job


JobDep = Annotated[dict[str, Any], Depends(get_job)]
