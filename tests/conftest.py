"""Shared fixtures: the real data in ../shared/data and small sequences."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
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
