"""An uploaded sequence keeps its name in a job's events and result files (before: "sequence",
the stored copy's name)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from strep_core.io.npz import write_npz
from strep_core.sim.lidar2d import simulate_2d


def test_an_upload_keeps_its_file_name(tmp_path: Path) -> None:
    path = tmp_path / "my-corridor.npz"
    write_npz(simulate_2d(3, frames=8), path)
    settings = Settings(data_dir=tmp_path / "data", worker_threads=1, max_concurrent_jobs=1, viewer_enabled=False)
    with TestClient(create_app(settings)) as client:
        with path.open("rb") as f:
            seq = client.post("/api/sequences", files={"file": ("my-corridor.npz", f)}).json()
        assert seq["name"] == "my-corridor"
        job = client.post("/api/jobs", json={"sequence_id": seq["id"], "method": "identity"}).json()
        deadline = time.monotonic() + 120
        while (status := client.get(f"/api/jobs/{job['id']}").json()["status"]) not in ("succeeded", "failed"):
            assert time.monotonic() < deadline, "the job did not finish"
            time.sleep(0.2)
        assert status == "succeeded"
        metrics = client.get(f"/api/jobs/{job['id']}/files/metrics.json").json()
        assert metrics["sequence"] == "my-corridor"
        with client.stream("GET", f"/api/jobs/{job['id']}/events") as events:
            text = "".join(events.iter_text())
        start = next(line for line in text.splitlines() if line.startswith("data:") and '"kind":"start"' in line)
        assert json.loads(start[5:])["sequence"] == "my-corridor"
