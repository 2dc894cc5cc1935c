"""House rules that a grep cannot prove: checked in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys

FORBIDDEN = ("fastapi", "uvicorn", "starlette", "viser", "rerun", "ray")


def test_strep_core_imports_no_web_viewer_or_cluster_code() -> None:
    code = (
        "import sys\n"
        "import strep_core, strep_core.cli, strep_core.runner, strep_core.bench, strep_core.sim\n"
        "from strep_core.methods import available\n"
        "available()\n"
        "import strep_core.io, strep_core.samples\n"
        f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"strep_core pulled in: {out}"


def test_importing_the_package_is_light() -> None:
    """`import strep_core` must not drag in Open3D or torch (the CLI starts fast)."""
    code = "import sys, strep_core, strep_core.cli; print(sorted({'open3d', 'torch'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
