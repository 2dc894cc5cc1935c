"""The web page's modules (static/js) type-check: TypeScript over their JSDoc types, installed
from the project's package.json / package-lock.json (``npm ci``; .ci/run does it)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TSC = ROOT / "node_modules" / ".bin" / "tsc"


def test_the_page_type_checks() -> None:
    if not TSC.exists():
        reason = "TypeScript is not installed (npm ci, from package-lock.json)"
        if os.environ.get("CI"):
            pytest.fail(reason, pytrace=False)
        pytest.skip(reason)
    done = subprocess.run([str(TSC), "-p", "tsconfig.json"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    listed = subprocess.run(
        [str(TSC), "-p", "tsconfig.json", "--listFilesOnly"], cwd=ROOT, capture_output=True, text=True, timeout=120
    ).stdout
    for module in ("api", "events", "state", "views", "charts", "main"):
        assert f"static/js/{module}.js" in listed, module
