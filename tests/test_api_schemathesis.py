"""Property-based API tests: schemathesis generates requests from the OpenAPI schema.

Whatever it sends, the service answers without a server error (5xx), with status codes and
bodies its schema documents. Examples per operation are bounded to keep this under a minute.

The schema is taken from the application object (what ``/openapi.json`` serves) and the
calls go to the app in-process (ASGI); its lifespan, which opens the service in a
temporary data folder, starts with the first call and is stopped by the module fixture.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.python import asgi
from schemathesis.specs.openapi.checks import response_schema_conformance, status_code_conformance

from app.core.config import Settings
from app.main import create_app

MAX_EXAMPLES = 20
DATA_DIR = Path(tempfile.gettempdir()) / f"strep-schemathesis-{os.getpid()}"  # created by the service

app = create_app(Settings(data_dir=DATA_DIR, max_upload_bytes=64 * 1024, worker_threads=1))
schema = schemathesis.openapi.from_dict(app.openapi())
schema.app = app


@pytest.fixture(scope="module", autouse=True)
def stop_service() -> Iterator[None]:
    yield
    asgi.shutdown_lifespans()  # closes the service (and any worker) before its folder goes
    shutil.rmtree(DATA_DIR, ignore_errors=True)


def test_schema_is_what_the_app_serves() -> None:
    from fastapi.testclient import TestClient

    served = TestClient(app).get("/openapi.json")  # no lifespan: the schema needs no service
    assert served.status_code == 200
    assert served.json() == app.openapi()


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case: schemathesis.Case) -> None:
    case.call_and_validate(checks=[not_a_server_error, status_code_conformance, response_schema_conformance])
