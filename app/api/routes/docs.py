"""The interactive API documentation, served from this machine: Swagger UI at ``/docs``, ReDoc
at ``/redoc``, and the favicon.

FastAPI's own pages load their scripts from a CDN (cdn.jsdelivr.net), so without internet
``/docs`` is blank. Here the scripts and styles come from the ``fastapi-offline`` package
(installed with this one; it ships Swagger UI 5 and ReDoc 2 as files), mounted under
``/docs-assets``; ReDoc is told not to fetch Google Fonts, and its bundle is served with the
"API docs by Redocly" logo pointed at the local favicon (ReDoc 2 loads it from cdn.redoc.ly and
has no option to leave it out). No page of the service asks any other host for anything.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

log = logging.getLogger("strep.service")

ASSETS = "/docs-assets"
FAVICON = Path(__file__).resolve().parents[3] / "static" / "favicon.svg"
REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"  # in ReDoc 2's menu footer, unconditionally


def assets_dir() -> Path | None:
    """The folder of Swagger UI's and ReDoc's files (from ``fastapi-offline``), or None."""
    try:
        import fastapi_offline
    except ImportError:
        return None
    folder = Path(fastapi_offline.__file__).resolve().parent / "static"
    return folder if (folder / "swagger-ui-bundle.js").is_file() else None


def install_docs(app: FastAPI) -> None:
    """Add ``/docs``, ``/docs/oauth2-redirect``, ``/redoc`` and ``/favicon.ico`` to ``app``
    (created with ``docs_url=None, redoc_url=None``)."""
    favicon = "/favicon.ico"

    @app.get(favicon, include_in_schema=False)
    def favicon_ico() -> FileResponse:
        return FileResponse(FAVICON, media_type="image/svg+xml")

    folder = assets_dir()
    if folder is None:  # the API works on; the pages say what is missing instead of going blank
        log.warning("fastapi-offline is not installed: /docs and /redoc show only a note")
        note = (
            "<p>The API documentation needs the <code>fastapi-offline</code> package."
            " The schema is at <a href='/openapi.json'>/openapi.json</a>.</p>"
        )

        @app.get("/docs", include_in_schema=False)
        @app.get("/redoc", include_in_schema=False)
        def no_docs() -> HTMLResponse:
            return HTMLResponse(note)

        return
    redoc_js = (folder / "redoc.standalone.js").read_text(encoding="utf-8").replace(REDOC_LOGO, favicon)

    @app.get(f"{ASSETS}/redoc.standalone.js", include_in_schema=False)
    def redoc_bundle() -> Response:  # before the mount, which would serve the file as shipped
        return Response(redoc_js, media_type="text/javascript; charset=utf-8")

    app.mount(ASSETS, StaticFiles(directory=folder), name="docs-assets")
    title = f"{app.title} - API"
    openapi_url = app.openapi_url or "/openapi.json"
    oauth2_redirect = "/docs/oauth2-redirect"

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=openapi_url,
            title=title,
            oauth2_redirect_url=oauth2_redirect,
            swagger_js_url=f"{ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{ASSETS}/swagger-ui.css",
            swagger_favicon_url=favicon,
        )

    @app.get(oauth2_redirect, include_in_schema=False)
    def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=openapi_url,
            title=title,
            redoc_js_url=f"{ASSETS}/redoc.standalone.js",
            redoc_favicon_url=favicon,
            with_google_fonts=False,
        )
