"""An upload is read once, into the project's scene format; jobs register that scene."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from app.core.config import Settings
from app.main import create_app
from app.services.scenes import UPLOAD_SCENE
from strep_core.io.npz import read_npz, write_npz
from strep_core.sim.lidar2d import simulate_2d

FINAL = {"succeeded", "failed", "cancelled", "interrupted"}


def _wait(client: TestClient, job_id: str) -> dict[str, Any]:
    deadline = time.monotonic() + 120
    while (job := client.get(f"/api/jobs/{job_id}").json())["status"] not in FINAL:
        assert time.monotonic() < deadline, job
        time.sleep(0.05)
    return job


def test_jobs_register_the_scene_read_at_upload(tmp_path: Path, shared_data: Path) -> None:
    seq = simulate_2d(3, frames=8)
    write_npz(seq, tmp_path / "sim8.npz")
    settings = Settings(data_dir=tmp_path / "service", max_concurrent_jobs=1, worker_threads=1)
    with TestClient(create_app(settings)) as client:
        with (tmp_path / "sim8.npz").open("rb") as f:
            r = client.post("/api/sequences", files={"file": ("sim8.npz", f)}, data={"frames": "1:7"})
        assert r.status_code == 201, r.text
        upload = r.json()
        folder = settings.uploads_dir / upload["id"]
        scene = read_npz(folder / UPLOAD_SCENE)
        assert len(scene) == 6 and scene.indices.tolist() == [1, 2, 3, 4, 5, 6]  # the selection, applied once
        uploaded = read_npz(tmp_path / "sim8.npz")
        np.testing.assert_array_equal(scene.frames[0], uploaded.frames[1])  # exact, as read
        assert scene.meta["sensor"] == uploaded.meta["sensor"]
        # the file as uploaded is no longer read by jobs: spoil it, the job still runs on the scene
        (folder / "sequence.npz").write_bytes(b"not an npz any more")
        job = client.post("/api/jobs", json={"sequence_id": upload["id"], "method": "identity", "frames": "0:4"})
        done = _wait(client, job.json()["id"])
        assert done["status"] == "succeeded", done
        assert done["metrics"]["frames"] == 4
        # reader options of its own: the job reads the file as uploaded again (here: spoiled)
        log = shared_data / "carmen" / "intel-corrected.log.gz"
        with log.open("rb") as f:
            r = client.post("/api/sequences", files={"file": (log.name, f)}, data={"frames": "0:20"})
        assert r.status_code == 201, r.text
        carmen = r.json()
        plain = _wait(
            client, client.post("/api/jobs", json={"sequence_id": carmen["id"], "method": "identity"}).json()["id"]
        )
        body = {"sequence_id": carmen["id"], "method": "identity", "data": {"max_range": 5.0}}
        short = _wait(client, client.post("/api/jobs", json=body).json()["id"])
        assert plain["status"] == short["status"] == "succeeded"
        assert short["metrics"]["points"] < plain["metrics"]["points"]  # read again, with the option
        assert short["metrics"]["frames"] == plain["metrics"]["frames"] == 20  # the upload's selection kept


def test_an_exact_npz_reads_back_the_sequence_written(tmp_path: Path) -> None:
    seq = simulate_2d(4, frames=5)
    write_npz(seq, tmp_path / "x.npz", exact=True)
    back = read_npz(tmp_path / "x.npz")
    for a, b in zip(back.frames, seq.frames, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.origins, seq.origins)
    assert back.meta["sensor"] == seq.meta["sensor"]
    write_npz(seq, tmp_path / "y.npz")  # the default stays compact: float32
    assert read_npz(tmp_path / "y.npz").frames[0].dtype == np.float64
    assert (
        not np.array_equal(read_npz(tmp_path / "y.npz").frames[0], seq.frames[0]) or seq.frames[0].dtype == np.float32
    )
