"""Shared fixtures: the real data in ../shared/data and small sequences."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The demo methods (`strep_demo_methods`) are a test-only plugin: on the path of the tests, of the
# workers they spawn and of the servers they start (PYTHONPATH), never in the product.
PLUGINS = ROOT / "tests" / "plugins"
sys.path.insert(0, str(PLUGINS))
os.environ["PYTHONPATH"] = os.pathsep.join([str(PLUGINS), *filter(None, [os.environ.get("PYTHONPATH")])])
SHARED_DATA = Path(os.environ.get("STREP_SHARED_DATA", ROOT.parent / "shared" / "data"))

# Services started by the tests (and the servers they spawn) run without the 3D viewer unless a
# test enables it: no viser server on port 8080 per TestClient.
os.environ.setdefault("STREP_VIEWER_ENABLED", "false")
# TestClient sends "Host: testserver"; a service without a token accepts only local Host names.
os.environ.setdefault("STREP_ALLOWED_HOSTS", "testserver")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real sequences (``../shared/data`` beside the repository)."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}; set STREP_SHARED_DATA")
    return SHARED_DATA


@pytest.fixture(scope="session")
def v1_pose0(shared_data: Path):
    """DeepMapping's v1_pose0: 256 frames x 256 points, map pixels, with ground truth."""
    from strep_core.io.deepmapping import read_deepmapping

    return read_deepmapping(shared_data / "deepmapping_2d" / "v1_pose0.tar")


# Markers given by module (files whose tests all run a whole registration, or drive chromium);
# single slow tests carry @pytest.mark.slow themselves. Plain `pytest` leaves these out.
BROWSER_MODULES = {"test_browser.py"}
SLOW_MODULES = {"test_api_server.py", "test_live.py", "test_ray.py", "test_api_schemathesis.py"}  # servers, Ray
ACCURACY_MODULES = {"test_real3d.py", "test_turning.py", "test_scratch.py", "test_learned.py", "test_reproduce.py"}


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        name = item.path.name
        if name in BROWSER_MODULES:
            item.add_marker(pytest.mark.browser)
        if name in ACCURACY_MODULES:
            item.add_marker(pytest.mark.accuracy)
        if name in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
