"""Live viewing wired through the service: a recording per job and per comparison, the viser
viewer fed by the job event stream (live and reopened), ``strep run --rrd``, and the health
answer that points at the viewer.

Jobs run in real worker processes on ``sample:sim2d-small``. The viewer update rate with two
live jobs is measured here (printed; see docs/viewer.md).
"""

from __future__ import annotations

import json
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import FINAL, wait_until

from app.core.config import Settings
from app.main import create_app
from app.rrd import read_recording
from app.viewer.scene import poses_to_matrices
from strep_cli import main as strep_main
from strep_core.events import parse_event
from strep_core.io.poses import read_tum

SAMPLE = "sample:sim2d-small"
FRAMES = 64


def events_of(client: TestClient, job_id: str) -> list[Any]:
    """The job's stored progress events, parsed (through its SSE stream, which ends with the job)."""
    out = []
    with client.stream("GET", f"/api/jobs/{job_id}/events") as r:
        assert r.status_code == 200
        for line in r.iter_lines():
            if line.startswith("data:"):
                data = json.loads(line[5:])
                if data.get("kind") != "status":
                    out.append(parse_event(data))
    return out


def wait_comparison(client: TestClient, cid: str) -> dict[str, Any]:
    return wait_until(
        lambda: (c := client.get(f"/api/comparisons/{cid}").json())["status"] not in ("queued", "running") and c,
        what=f"comparison {cid}",
        timeout=120,
    )


def assert_poses_equal(recorded: np.ndarray, expected: np.ndarray) -> None:
    """Recorded poses are float32: compare to 1e-6 (rotations) and 1e-3 px (translations)."""
    assert recorded.shape == expected.shape
    np.testing.assert_allclose(recorded[:, :3, :3], expected[:, :3, :3], atol=1e-6)
    np.testing.assert_allclose(recorded[:, :3, 3], expected[:, :3, 3], atol=1e-3)


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    settings = Settings(
        data_dir=tmp_path_factory.mktemp("live"),
        plugins=["strep_demo_methods"],
        max_concurrent_jobs=2,
        worker_threads=1,
        viewer_enabled=True,
        viewer_port=0,  # any free port
    )
    with TestClient(create_app(settings)) as c:
        yield c


# ---- health ------------------------------------------------------------------------------------


def test_health_reports_the_viewer(client: TestClient) -> None:
    health = client.get("/api/health").json()
    viewer = client.app.state.service.viewer
    assert health["viewer_port"] == viewer.port > 0
    assert health["viewer_url"] == f"http://127.0.0.1:{viewer.port}/"
    with urllib.request.urlopen(health["viewer_url"], timeout=10) as page:  # viser's client is served there
        assert page.status == 200 and b"<html" in page.read(4096).lower()


def test_viewer_disabled(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path, viewer_enabled=False)
    with TestClient(create_app(settings)) as c:
        health = c.get("/api/health").json()
        assert (health["viewer_port"], health["viewer_url"]) == (None, None)
        assert c.app.state.service.viewer is None
        job = c.post("/api/jobs", json={"sequence_id": SAMPLE, "method": "identity"}).json()
        r = c.post(f"/api/jobs/{job['id']}/view")
        assert r.status_code == 409 and "viewer is disabled" in r.json()["detail"]


# ---- a job's own recording -------------------------------------------------------------------


def test_job_writes_its_recording(client: TestClient, tmp_path: Path) -> None:
    job = client.post("/api/jobs", json={"sequence_id": SAMPLE, "method": "icp"}).json()
    done = wait_until(lambda: (j := client.get(f"/api/jobs/{job['id']}").json())["status"] in FINAL and j, timeout=120)
    assert done["status"] == "succeeded", done
    assert "recording.rrd" in done["files"]
    r = client.get(f"/api/jobs/{job['id']}/files/recording.rrd")
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    path = tmp_path / "job.rrd"
    path.write_bytes(r.content)
    rec = read_recording(path)  # Rerun's own reader
    assert (rec.application_id, rec.recording_id, set(rec.runs)) == ("strep-studio", job["id"], {"icp"})
    paths = set(rec.entity_paths)
    assert {f"world/icp/frames/frame_{k}" for k in range(FRAMES)} <= paths
    assert {"world/icp/trajectory", "world/icp/map", "world/icp/ground_truth/trajectory", "metrics/icp/ate"} <= paths
    assert {"summary/icp", "logs/icp"} <= paths
    events = events_of(client, job["id"])
    (result,) = [e for e in events if e.kind == "result"]
    logged = sorted({e.iteration for e in events if e.kind == "iteration"} | {result.iterations})
    assert rec.runs["icp"].iterations == logged  # every progress event with poses, and the result
    assert len(logged) >= 6
    assert_poses_equal(rec.runs["icp"].last_poses, poses_to_matrices(result.poses))
    tum = client.get(f"/api/jobs/{job['id']}/files/trajectory.tum")
    (tmp_path / "t.tum").write_bytes(tum.content)
    np.testing.assert_allclose(
        rec.runs["icp"].last_poses[:, :3, 3], read_tum(tmp_path / "t.tum").poses[:, :3, 3], atol=1e-3
    )
    # atomic: no temporary left beside the result files
    names = {p.name for p in client.app.state.service.jobs.result_dir(job["id"]).iterdir()}
    assert names == set(done["files"])
    # the scene its worker wrote (the service reads this, never the upload): the frames it registered
    scene = client.app.state.service.loader.load(job["id"])
    assert client.app.state.service.jobs.scene_path(job["id"]).is_file()
    assert (len(scene), scene.name) == (FRAMES, "sim2d-small")
    np.testing.assert_array_equal(scene.indices, read_tum(tmp_path / "t.tum").stamps)


# ---- a comparison: combined recording and the live viewer ------------------------------------


def test_comparison_recording_and_viewer(client: TestClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the viewer and the recordings read the scenes the workers wrote: this process reads no input
    import strep_core.io
    import strep_core.samples

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the service process read an input")

    monkeypatch.setattr(strep_core.samples, "load_sample", never)
    monkeypatch.setattr(strep_core.io, "load_sequence", never)
    service = client.app.state.service
    viewer = service.viewer
    iterations = 12
    body = {
        "sequence_id": SAMPLE,
        "methods": ["strep", "strep-nolink"],
        "config": {"optim": {"iterations": iterations, "event_interval": 1}},
    }
    cmp = client.post("/api/comparisons", json=body).json()
    assert cmp["files"] == []
    ids = {j["method"]: j["id"] for j in cmp["jobs"]}
    # live: both jobs appear in the viewer under the comparison, which is shown
    wait_until(lambda: set(ids.values()) <= set(viewer.jobs()), what="jobs in the viewer", timeout=60)
    assert {viewer.jobs()[j]["group"] for j in ids.values()} == {cmp["id"]}
    r = client.get(f"/api/comparisons/{cmp['id']}/files/recording.rrd")
    assert r.status_code == 409 and "running" in r.json()["detail"]  # (or queued)
    done = wait_comparison(client, cmp["id"])
    assert done["status"] == "succeeded", done

    # the viewer got every event (the store's log), its last state is the result
    assert viewer.wait_idle(10)
    assert viewer.replay_state()["selected"] == cmp["id"]
    for method, job_id in ids.items():
        info = viewer.jobs()[job_id]
        assert info["finished"] and info["iteration"] == iterations and info["label"] == method
        assert info["shown_iteration"] == iterations and info["pushes"] >= 2
        events = events_of(client, job_id)
        assert info["events"] == len(events)  # every stored progress event reached the viewer
        its = [e for e in events if e.kind == "iteration"]
        result = next(e for e in events if e.kind == "result")  # (the stage "write" comes after it)
        live = result.wall_seconds - its[0].elapsed
        print(
            f"\n{method} (two live jobs): {len(its) / live:.2f} iteration events/s, "
            f"{info['pushes'] / live:.2f} viewer pushes/s over {live:.1f} s"
        )

    # the comparison's recording: written shortly after its last job, both methods side by side
    r = wait_until(
        lambda: (x := client.get(f"/api/comparisons/{cmp['id']}/files/recording.rrd")).status_code != 409 and x,
        what="comparison recording",
        timeout=60,
        step=0.2,
    )
    assert r.status_code == 200, r.text
    assert client.get(f"/api/comparisons/{cmp['id']}").json()["files"] == ["recording.rrd"]
    path = tmp_path / "cmp.rrd"
    path.write_bytes(r.content)
    rec = read_recording(path)
    assert (rec.recording_id, set(rec.runs)) == (cmp["id"], {"strep", "strep-nolink"})
    for key in ("strep", "strep-nolink"):
        assert {f"world/{key}/frames/frame_0", f"world/{key}/trajectory", f"metrics/{key}/loss/total"} <= set(
            rec.entity_paths
        )
        events = events_of(client, ids[key])
        (result,) = [e for e in events if e.kind == "result"]
        assert rec.runs[key].iterations == list(range(0, iterations + 1))  # 0: the starting poses
        assert_poses_equal(rec.runs[key].last_poses, poses_to_matrices(result.poses))
        # ... and each job's own recording says the same
        own = tmp_path / f"{key}.rrd"
        own.write_bytes(client.get(f"/api/jobs/{ids[key]}/files/recording.rrd").content)
        assert_poses_equal(read_recording(own).runs[key].last_poses, rec.runs[key].last_poses)
    assert rec.runs["strep-nolink"].offset[0] > rec.runs["strep"].offset[0] + 500  # side by side (px)

    # reopened on demand from the store once the viewer has dropped them
    for job_id in ids.values():
        viewer.remove_job(job_id)
    assert not set(ids.values()) & set(viewer.jobs())
    r = client.post(f"/api/jobs/{ids['strep']}/view")  # a job of a comparison: the whole comparison
    assert r.status_code == 200, r.text
    assert r.json() == {"viewer_url": viewer.url, "group": cmp["id"], "jobs": list(ids.values())}
    assert viewer.wait_idle(10)
    for job_id in ids.values():
        info = viewer.jobs()[job_id]
        assert info["finished"] and info["history"] == iterations + 1 and info["group"] == cmp["id"]
    assert viewer.replay_state()["selected"] == cmp["id"]
    viewer.set_replay(iteration=3)  # replay works on the reopened run
    assert viewer.wait_idle(10)
    assert {viewer.jobs()[j]["shown_iteration"] for j in ids.values()} == {3}
    viewer.set_replay(live=True)

    assert client.post("/api/comparisons/cmp_nope/view").status_code == 404
    assert client.post("/api/jobs/job_nope/view").status_code == 404
    assert client.get(f"/api/comparisons/{cmp['id']}/files/map.ply").status_code == 404
    assert client.get("/api/comparisons/cmp_nope/files/recording.rrd").status_code == 404


def test_viewer_throttles_two_live_jobs(client: TestClient) -> None:
    """Two jobs emitting an event every 20 ms: each is pushed at most once per throttle interval.

    The window lasts until each job was pushed at least once (a pusher starved by a loaded
    machine only makes it longer) and the bound is taken over the measured window, so load
    changes the figures, not the verdict; the real update rate is measured by
    ``benchmarks/viewer_rate.py``.
    """
    viewer = client.app.state.service.viewer
    steps = 200  # x 20 ms
    body = {
        "sequence_id": SAMPLE,
        "methods": ["demo-sleep", "demo-stubborn"],
        "config": {"optim": {"iterations": steps, "event_interval": 1}},
    }
    cmp = client.post("/api/comparisons", json=body).json()
    ids = [j["id"] for j in cmp["jobs"]]

    def iterations() -> list[int]:
        jobs = viewer.jobs()
        return [jobs[j]["iteration"] or 0 if j in jobs else 0 for j in ids]

    wait_until(lambda: min(iterations()) >= 25, what="both jobs live", timeout=120)
    t0, pushes0, its0 = time.monotonic(), dict(viewer.stats.pushes_by_job), iterations()

    def pushed() -> bool:
        now = viewer.stats.pushes_by_job
        return all(now.get(j, 0) > pushes0.get(j, 0) for j in ids)

    wait_until(
        lambda: pushed() and (max(iterations()) >= steps - 25 or time.monotonic() - t0 > 3),
        what="progress and a push of each job",
        timeout=120,
    )
    t1, pushes1, its1 = time.monotonic(), dict(viewer.stats.pushes_by_job), iterations()
    pushes = [pushes1[j] - pushes0.get(j, 0) for j in ids]
    events = [b - a for a, b in zip(its0, its1, strict=True)]
    for n_push, n_events in zip(pushes, events, strict=True):
        assert 1 <= n_push <= n_events + 1  # shown live, never more often than it changed ...
        assert n_push <= (t1 - t0) / viewer.interval + 2  # ... nor more than once an interval
    assert wait_comparison(client, cmp["id"])["status"] == "succeeded"


# ---- the CLI ---------------------------------------------------------------------------------


def test_cli_rrd(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, rrd = tmp_path / "out", tmp_path / "run.rrd"
    code = strep_main(["run", SAMPLE, "-m", "icp", "--frames", "0:24", "-o", str(out), "--rrd", str(rrd), "-q"])
    assert code == 0
    assert str(rrd) in capsys.readouterr().out
    rec = read_recording(rrd)
    assert rec.recording_id.startswith("cli-") and set(rec.runs) == {"icp"}
    assert {f"world/icp/frames/frame_{k}" for k in range(24)} <= set(rec.entity_paths)
    assert "world/icp/frames/frame_24" not in rec.entity_paths  # the frame selection applies
    metrics = json.loads((out / "metrics.json").read_text())
    assert rec.runs["icp"].iterations[-1] == metrics["iterations"] == 24
    np.testing.assert_allclose(
        rec.runs["icp"].last_poses[:, :3, 3], read_tum(out / "trajectory.tum").poses[:, :3, 3], atol=1e-3
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "run.rrd"]  # no temporary left
