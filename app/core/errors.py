"""Turning errors into HTTP answers: every error is ``{"detail": "one readable line"}``.

`strep_core` raises typed errors and knows nothing of HTTP; the mapping lives here, once:

========================================= ====== ==========================================
error                                     status meaning
========================================= ====== ==========================================
`ConfigError`, `MethodError`              422    the request's options are invalid
`FormatError`, `SequenceError`, others    400    the uploaded data cannot be used
========================================= ====== ==========================================
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Route

from app.services.uploads import UploadError
from strep_core.errors import ConfigError, MethodError, StrepError

STREP_ERROR_STATUS: tuple[tuple[type[StrepError], int], ...] = (
    (ConfigError, 422),
    (MethodError, 422),
    (StrepError, 400),
)


def status_for(exc: StrepError) -> int:
    for cls, status in STREP_ERROR_STATUS:
        if isinstance(exc, cls):
            return status
    return 400


def _loc(loc: Sequence[Any]) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] == "body":
        parts = parts[1:]
    return ".".join(parts) or "body"


def validation_detail(errors: list[dict[str, Any]]) -> tuple[str, list[dict[str, Any]]]:
    """One line for all problems (``field.path: message; ...``) and a JSON-safe list of them."""
    simple = [
        {"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
        for e in errors
    ]
    for e, raw in zip(simple, errors, strict=True):
        if e["type"] == "json_invalid":  # loc is ("body", offset): say what and where
            reason = (raw.get("ctx") or {}).get("error", "")
            e["msg"] = f"the body is not valid JSON ({reason} at position {e['loc'][-1]})" if reason else e["msg"]
            e["loc"] = ["body"]
    line = "; ".join(f"{_loc(e['loc'])}: {e['msg']}" for e in simple)
    return line or "invalid request", simple


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(StrepError)
    async def strep_error(request: Request, exc: StrepError) -> JSONResponse:
        return JSONResponse({"detail": str(exc) or type(exc).__name__}, status_code=status_for(exc))

    @app.exception_handler(UploadError)
    async def upload_error(request: Request, exc: UploadError) -> JSONResponse:
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        line, errors = validation_detail(list(exc.errors()))
        return JSONResponse({"detail": line, "errors": errors}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:  # Starlette names only the first route of the path that matched
            headers["Allow"] = ", ".join(allowed_methods(request.app, request.scope))
        return JSONResponse({"detail": detail}, status_code=exc.status_code, headers=headers or None)


def allowed_methods(app: Any, scope: dict[str, Any]) -> list[str]:
    """Every method the request's path answers, sorted (a 405's ``Allow``): the operations the
    OpenAPI schema documents for it, else those of the app's own routes (the page, the docs)."""
    path = scope.get("path", "")
    methods: set[str] = set()
    for template, operations in app.openapi().get("paths", {}).items():
        if _path_regex(template).fullmatch(path):
            methods |= {m.upper() for m in operations if m.upper() in HTTP_METHODS}
    if not methods:
        for route in app.router.routes:
            if isinstance(route, Route) and route.methods and route.matches(scope)[0] != Match.NONE:
                methods |= route.methods
    return sorted(methods)


HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "TRACE"})


@functools.lru_cache(maxsize=256)
def _path_regex(template: str) -> re.Pattern[str]:
    """``/api/jobs/{job_id}`` as a regular expression (a parameter is one path segment)."""
    parts = re.split(r"(\{[^/{}]+\})", template)
    return re.compile("".join("[^/]+" if p.startswith("{") else re.escape(p) for p in parts))
