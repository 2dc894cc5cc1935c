"""The FastAPI application: ``create_app(settings)``.

Run it with ``strep serve`` (see `app.server`), or ``uvicorn --factory app.main:create_app``.
Either way the settings are checked alike: ``STREP_HOST`` off loopback without
``STREP_API_TOKEN`` raises `InsecureSettings`, and without a token every request from
another machine (``uvicorn --host 0.0.0.0``), with a foreign Host or a cross-site Origin is
refused (see `app.core.guard`).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

import strep_core
from app.api.main import api_router
from app.api.routes.docs import install_docs
from app.core.config import Settings, get_settings
from app.core.errors import install_error_handlers
from app.core.guard import RequestGuard
from app.services import Service

log = logging.getLogger("strep.service")

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"

DESCRIPTION = """Unsupervised global registration of temporal sequences of 2D/3D point clouds.

Upload a sequence, queue jobs (one method each) or comparisons (several methods, side by side),
follow them live with Server-Sent Events and download their trajectory, map and metrics.
Errors are `{"detail": "..."}`. See docs/api.md.
"""


def create_app(settings: Settings | None = None) -> FastAPI:
    """The application. Its lifespan opens the service (store, workers) and closes it."""
    settings = settings or get_settings()
    settings.check_secure()  # the same refusal as `strep serve`, for ``uvicorn --factory`` too

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = await run_in_threadpool(_open_service, settings)
        app.state.service = service
        try:
            yield
        finally:
            app.state.service = None
            await run_in_threadpool(service.close)

    app = FastAPI(
        title="STREP Studio",
        version=strep_core.__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # served from local files instead (app.api.routes.docs): no CDN
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.service = None
    install_error_handlers(app)
    app.add_middleware(RequestGuard, settings=settings)  # inside CORS, so preflights get their answer
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "Last-Event-ID"],
        )
    app.include_router(api_router)
    install_docs(app)
    _mount_page(app)
    _document_errors(app, token_required=settings.api_token is not None)
    return app


def _mount_page(app: FastAPI) -> None:
    """The web page: ``/`` and its assets under ``/static`` (all served locally, no CDN)."""
    if not STATIC_DIR.is_dir():  # an install without the page: the API still works
        log.warning("no static/ folder at %s: the web page is not served", STATIC_DIR)
        return
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html")


def _open_service(settings: Settings) -> Service:
    service = Service(settings)
    try:
        service.start()
    except BaseException:
        service.close()
        raise
    return service


def _document_errors(app: FastAPI, *, token_required: bool) -> None:
    """Describe 422 answers as they are: ``{"detail": str, "errors": [...]}``; error answers as
    JSON on every route (FastAPI gives them the media type of a route's success, such as the
    event stream's ``text/event-stream``); without a token
    the bearer scheme is optional (an empty security requirement beside it), as the service is."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            from fastapi.openapi.utils import get_openapi

            schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            schemas = schema.setdefault("components", {}).setdefault("schemas", {})
            schemas["HTTPValidationError"] = {
                "title": "HTTPValidationError",
                "type": "object",
                "required": ["detail"],
                "properties": {
                    "detail": {"type": "string", "title": "Detail"},
                    "errors": {"type": "array", "items": {"type": "object"}, "title": "Errors"},
                },
            }
            schemas.pop("ValidationError", None)
            for path in schema.get("paths", {}).values():  # errors are JSON, whatever a route's success is
                for op in path.values():
                    for status, answer in op.get("responses", {}).items() if isinstance(op, dict) else ():
                        content = answer.get("content", {})
                        if status[:1] in "45" and content and "application/json" not in content:
                            answer["content"] = {"application/json": next(iter(content.values()))}
            if not token_required:
                for path in schema.get("paths", {}).values():
                    for op in path.values():
                        if isinstance(op, dict) and op.get("security") and {} not in op["security"]:
                            op["security"].append({})
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
