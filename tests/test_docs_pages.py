"""The API documentation pages and the favicon are served from this machine (no CDN)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    settings = Settings(data_dir=tmp_path_factory.mktemp("docs"), worker_threads=1, max_concurrent_jobs=1)
    with TestClient(create_app(settings)) as c:
        yield c


def local_urls(html: str) -> list[str]:
    """Every src/href and url in a page; fails on one that names another host."""
    urls = re.findall(r"""(?:src|href)=["']([^"']+)["']""", html) + re.findall(r"""url: ?["']([^"']+)["']""", html)
    foreign = [u for u in urls if re.match(r"^(https?:)?//", u)]
    assert not foreign, foreign
    return urls


@pytest.mark.parametrize(("page", "assets"), [("/docs", 2), ("/redoc", 1)])
def test_docs_pages_load_their_assets_from_this_service(client: TestClient, page: str, assets: int) -> None:
    r = client.get(page)
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert "cdn.jsdelivr.net" not in r.text and "fonts.googleapis" not in r.text
    scripts = [u for u in local_urls(r.text) if u.startswith("/docs-assets/")]
    assert len(scripts) == assets, scripts
    for url in scripts:
        asset = client.get(url)
        assert asset.status_code == 200 and len(asset.content) > 100_000, url  # the real bundles, not a stub


def test_favicon(client: TestClient) -> None:
    r = client.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/svg+xml")
    assert r.content.startswith(b"<svg")
    page = client.get("/").text
    assert '<link rel="icon" href="/static/favicon.svg"' in page
    svg = Path(__file__).resolve().parents[1] / "static" / "favicon.svg"
    assert client.get("/static/favicon.svg").content == svg.read_bytes()


def test_the_page_shows_the_service_defaults_and_sends_none(client: TestClient) -> None:
    """One default iteration count everywhere (before: the page sent 150, the CLI used 300): the
    page shows the service's defaults (GET /api/starts, no copy in the page), and sends a count
    only when one is typed."""
    from strep_core.config import RunConfig
    from strep_core.profiles import START_OVERLAYS

    root = Path(__file__).resolve().parents[1] / "static"
    starts = client.get("/api/starts").json()
    default = RunConfig().optim.iterations
    expected = {  # the start's overlay over the defaults (strep_core.resolve applies it)
        start: START_OVERLAYS[start].get("optim", {}).get("iterations", default) for start in ("scratch", "pose-graph")
    }
    assert {s["name"]: s["iterations"] for s in starts["data"]} == expected
    assert expected["scratch"] != expected["pose-graph"]
    assert starts["default"] == "scratch"  # the first preset: from scratch
    html = (root / "index.html").read_text()
    assert "data-iterations" not in html
    assert re.search(r'<input type="number" id="iterations"(?![^>]*value=)[^>]*>', html)  # empty by default
    js = (root / "js" / "main.js").read_text()
    assert "if (iterations != null) optim.iterations = iterations;" in js


def test_redoc_loads_no_logo_from_a_cdn(client: TestClient) -> None:
    """ReDoc 2 shows "API docs by Redocly" with a logo from cdn.redoc.ly; the served bundle
    points it at the local favicon (before: the one request /redoc made to another host)."""
    bundle = client.get("/docs-assets/redoc.standalone.js")
    assert bundle.status_code == 200 and "javascript" in bundle.headers["content-type"]
    assert "cdn.redoc.ly" not in bundle.text and 'src:"/favicon.ico"' in bundle.text
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        assert not re.findall(r"(?:src|href)=[\"'](?:https?:)?//", html), page
