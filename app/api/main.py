"""All API routes under ``/api``, behind the bearer-token check."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from app.api.deps import require_token
from app.api.routes import comparisons, health, jobs, sequences, state
from app.models import ErrorPublic

api_router = APIRouter(
    prefix="/api",
    dependencies=[Depends(require_token)],
    # the answers of app.core.guard.RequestGuard, which runs before any route
    responses={
        401: {"model": ErrorPublic, "description": "missing or invalid bearer token (when a token is set)"},
        403: {"model": ErrorPublic, "description": "without a token: a client off this machine or a cross-site Origin"},
        413: {"model": ErrorPublic, "description": "request body over STREP_MAX_BODY_BYTES"},
        421: {"model": ErrorPublic, "description": "without a token: a Host header that does not name this machine"},
    },
)
api_router.include_router(health.router)
api_router.include_router(sequences.router)
api_router.include_router(jobs.router)
api_router.include_router(comparisons.router)
api_router.include_router(state.router)
