"""Dependencies shared by the routes (``Annotated`` aliases)."""

from __future__ import annotations

import hmac
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.core.config import Settings
from app.services import Service

bearer = HTTPBearer(auto_error=False, description="STREP_API_TOKEN, when the service has one")


def get_service(request: Request) -> Service:
    service = getattr(request.app.state, "service", None)
    if service is None:
        raise HTTPException(503, "the service is starting or stopping")
    return service


ServiceDep = Annotated[Service, Depends(get_service)]


def get_settings(service: ServiceDep) -> Settings:
    return service.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def require_token(
    service: ServiceDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """With ``STREP_API_TOKEN`` set, every API call needs ``Authorization: Bearer <token>``."""
    token = service.settings.api_token
    if token is None:
        return
    given = credentials.credentials if credentials is not None else ""
    if not hmac.compare_digest(given.encode(), token.get_secret_value().encode()):
        raise HTTPException(401, "missing or invalid bearer token", headers={"WWW-Authenticate": "Bearer"})


def get_job(job_id: str, service: ServiceDep) -> dict[str, Any]:
    job = service.store.get_job(job_id)
    if job is None:
        raise HTTPException(404, f"job {job_id!r} not found")
    return job


JobDep = Annotated[dict[str, Any], Depends(get_job)]
