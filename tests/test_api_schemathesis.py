"""Property-based API tests: schemathesis generates requests from the OpenAPI schema.

Whatever it sends, the service answers without a server error (5xx), with status codes,
headers, content types and bodies its schema documents: every check schemathesis has
(``call_and_validate`` with none named runs them all), positive and negative data alike.

A valid sequence and a finished job are seeded first, and the generated requests use them:
``sequence_id`` in a body names the seeded sequence (so ``POST /api/jobs`` and
``/api/comparisons`` get past the 404 and create jobs when the rest of the body is valid), and
``job_id`` / ``sequence_id`` in paths name the seeded job and sequence (a finished job: its
event stream ends, its files download; a delete of the seeded sequence is left to random ids,
so the seed stays). Examples per operation are bounded to keep this short in the suite; a
longer run sets ``STREP_SCHEMATHESIS_EXAMPLES`` (e.g. 300; see docs/design/hardening.md).

The schema is taken from the application object (what ``/openapi.json`` serves) and the
calls go to the app in-process (ASGI); its lifespan, which opens the service in a
temporary data folder, starts with the first call and is stopped by the module fixture.
"""

from __future__ import annotations

import io
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.config import SchemathesisConfig
from schemathesis.generation import GenerationMode
from schemathesis.python import asgi

from app.core.config import Settings
from app.main import create_app

MAX_EXAMPLES = int(os.environ.get("STREP_SCHEMATHESIS_EXAMPLES", "20"))
DATA_DIR = Path(tempfile.gettempdir()) / f"strep-schemathesis-{os.getpid()}"  # created by the service
BASE = "http://testserver"

app = create_app(Settings(data_dir=DATA_DIR, max_upload_bytes=64 * 1024, worker_threads=1, max_concurrent_jobs=1))
# What the schema cannot say: an upload's content is a valid sequence of a known format (400
# otherwise), and a run's options hold together (a registered method, freeze with from_model,
# a nonzero yaw axis...: 422 otherwise). On these three operations a schema-valid request may
# be refused with those two statuses; everywhere else the default expectations hold.
CONFIG = SchemathesisConfig.from_str(
    """
[[operations]]
include-path-regex = "^/api/(sequences|jobs|comparisons)$"
include-method = "POST"
checks.positive_data_acceptance.expected-statuses = ["2xx", "400", "401", "403", "404", "409", "422", "429"]
"""
)
schema = schemathesis.openapi.from_dict(app.openapi(), config=CONFIG)
schema.app = app


def seed_npz() -> bytes:
    """A small valid 2D sequence: 6 frames of 24 points with ground-truth poses."""
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(3)[None], 6, axis=0)
    poses[:, :2, 2] = rng.normal(size=(6, 2))
    buf = io.BytesIO()
    np.savez(buf, points=rng.normal(size=(6 * 24, 2)) * 10, counts=np.full(6, 24), poses=poses)
    return buf.getvalue()


@pytest.fixture(scope="module")
def seeded() -> Iterator[dict[str, str]]:
    """An uploaded sequence and a finished identity job on it; the service is stopped after."""
    try:
        with asgi.get_client(app) as client:  # starts the app's lifespan, shared with the generated calls
            ids = seed(client)
        yield ids
    finally:
        asgi.shutdown_lifespans()  # closes the service (and any worker) before its folder goes
        shutil.rmtree(DATA_DIR, ignore_errors=True)


def seed(client: asgi.ASGIClient) -> dict[str, str]:
    """Upload a sequence and run an identity job on it to its end."""
    seq = client.post(f"{BASE}/api/sequences", files={"file": ("seed.npz", seed_npz())})
    assert seq.status_code == 201, seq.text
    seq_id = seq.json()["id"]
    job = client.post(f"{BASE}/api/jobs", json={"sequence_id": seq_id, "method": "identity"})
    assert job.status_code == 201, job.text
    job_id = job.json()["id"]
    deadline = time.monotonic() + 120
    while client.get(f"{BASE}/api/jobs/{job_id}").json()["status"] != "succeeded":
        assert time.monotonic() < deadline, "the seeded job did not finish"
        time.sleep(0.05)
    return {"sequence_id": seq_id, "job_id": job_id}


def use_seeds(case: schemathesis.Case, seeds: dict[str, str]) -> None:
    """Point the generated ids of a positive case at the seeded sequence and job (a negative
    case keeps its ids: its id may be what makes it invalid)."""
    if case.meta is not None and case.meta.generation.mode != GenerationMode.POSITIVE:
        return
    if isinstance(case.body, dict) and isinstance(case.body.get("sequence_id"), str):
        case.body["sequence_id"] = seeds["sequence_id"]
    params = case.path_parameters or {}
    if isinstance(params.get("job_id"), str):
        params["job_id"] = seeds["job_id"]
    if isinstance(params.get("sequence_id"), str) and case.method.upper() != "DELETE":
        params["sequence_id"] = seeds["sequence_id"]


def test_schema_is_what_the_app_serves() -> None:
    from fastapi.testclient import TestClient

    served = TestClient(app).get("/openapi.json")  # no lifespan: the schema needs no service
    assert served.status_code == 200
    assert served.json() == app.openapi()


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
def test_every_check_passes(case: schemathesis.Case, seeded: dict[str, str]) -> None:
    use_seeds(case, seeded)
    case.call_and_validate()


def test_generated_jobs_were_created(seeded: dict[str, str]) -> None:
    """Runs after the generated calls: some got past validation and created jobs on the seed
    (the seeded job is one; a comparison or a job from the generated bodies adds more)."""
    with asgi.get_client(app) as client:
        jobs = client.get(f"{BASE}/api/jobs", params={"sequence_id": seeded["sequence_id"], "limit": 1})
    assert jobs.status_code == 200, jobs.text
    assert jobs.json()["count"] > 1
