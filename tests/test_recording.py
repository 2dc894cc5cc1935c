"""The Rerun recording sink: real runs recorded, read back with Rerun's own reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.rrd import ComparisonRecorder, RerunRecorder, cli_sink, read_recording, write_recording
from app.viewer.scene import poses_to_matrices
from strep_core.config import RunConfig
from strep_core.events import ListSink, MultiSink, ResultEvent
from strep_core.methods import available, run
from strep_core.pipeline import load_input


@pytest.fixture(scope="module")
def sim2d():
    return load_input("sample:sim2d-small")


@pytest.fixture(scope="module")
def sim3d():
    return load_input("sample:sim3d-room")


def _record(seq, config: RunConfig, path: Path, run_id: str) -> tuple[ListSink, object]:
    events = ListSink()
    recorder = RerunRecorder(path, recording_id=run_id, sequence=seq)
    result = run(seq, config, sink=MultiSink([events, recorder]))
    assert recorder.closed and recorder.failed is None  # closed itself on the ResultEvent
    return events, result


def _assert_last_poses(summary_run, events: ListSink, unit_scale: float) -> None:
    (res,) = events.of_kind("result")
    assert isinstance(res, ResultEvent)
    expected = poses_to_matrices(res.poses)
    assert summary_run.last_poses.shape == expected.shape
    # float32 storage: relative precision 2^-24 of the largest coordinate
    np.testing.assert_allclose(summary_run.last_poses[:, :3, :3], expected[:, :3, :3], atol=1e-6)
    np.testing.assert_allclose(summary_run.last_poses[:, :3, 3], expected[:, :3, 3], atol=4e-7 * unit_scale)


def _no_temporaries(folder: Path) -> None:
    names = sorted(p.name for p in folder.iterdir())
    assert all(n.endswith(".rrd") and not n.startswith(".") for n in names), names


def test_icp_2d_recording_reads_back(sim2d, tmp_path: Path) -> None:
    path = tmp_path / "icp.rrd"
    events, result = _record(sim2d, RunConfig(method="icp"), path, "job-icp")
    s = read_recording(path)
    assert (s.application_id, s.recording_id, s.has_blueprint) == ("strep-studio", "job-icp", True)
    assert s.views == ["ATE", "Loss", "Registration", "Summary"]
    assert set(s.runs) == {"icp"}
    k = len(sim2d)
    expected = {f"world/icp/frames/frame_{i}" for i in range(k)} | {
        "world",
        "world/icp",
        "world/icp/label",
        "world/icp/frames",
        "world/icp/trajectory",
        "world/icp/map",
        "world/icp/ground_truth/trajectory",
        "world/icp/ground_truth/map",
        "metrics/icp/ate",
        "summary/icp",
        "logs/icp",
    }
    assert expected <= set(s.entity_paths)
    r = s.runs["icp"]
    its = [e.iteration for e in events.of_kind("iteration") if e.poses is not None]
    assert r.iterations == its == [10, 20, 30, 40, 50, 60, 64]
    assert r.label == "icp"
    # map every 5 iterations -> at every event here (events come every 10 frames), and at the end
    assert r.map_iterations == its
    _assert_last_poses(r, events, unit_scale=1100.0)  # px coordinates up to ~1100
    # the ATE curve: the events' values, then the final metric at the last iteration
    x, y = r.scalars["ate"]
    assert x[-1] == 64 and y[-1] == pytest.approx(result.metrics["ate"], rel=1e-6)
    assert path.stat().st_size < 4_000_000
    _no_temporaries(tmp_path)


def test_identity_3d_recording(sim3d, tmp_path: Path) -> None:
    path = tmp_path / "identity.rrd"
    events, _ = _record(sim3d, RunConfig(method="identity"), path, "job-id3d")
    s = read_recording(path)
    r = s.runs["identity"]
    assert r.iterations == [0]  # no iteration events: the result's poses at iteration 0
    assert len(r.last_poses) == len(sim3d)
    _assert_last_poses(r, events, unit_scale=10.0)
    np.testing.assert_allclose(r.last_poses, np.broadcast_to(np.eye(4), r.last_poses.shape), atol=1e-7)
    assert {f"world/identity/frames/frame_{i}" for i in range(len(sim3d))} <= set(s.entity_paths)
    _no_temporaries(tmp_path)


@pytest.mark.skipif("strep" not in available(), reason="the learned methods have not landed")
def test_strep_recording_has_losses_and_final_poses(sim2d, tmp_path: Path) -> None:
    path = tmp_path / "strep.rrd"
    config = RunConfig(method="strep", optim={"iterations": 10, "event_interval": 5}, threads=1)
    events, _ = _record(sim2d, config, path, "job-strep")
    s = read_recording(path)
    r = s.runs["strep"]
    assert r.iterations == [0, 5, 10]  # 0: the starting poses and their ATE, before any loss
    terms = set(events.of_kind("iteration")[1].losses)
    assert {"total"} <= terms
    assert {f"loss/{t}" for t in terms} <= set(r.scalars)
    for t in terms:
        x, y = r.scalars[f"loss/{t}"]
        assert list(x) == [5, 10]
        assert np.all(np.isfinite(y))
    _assert_last_poses(r, events, unit_scale=1100.0)
    size = path.stat().st_size
    assert 100_000 < size < 3_000_000, size  # 3 map snapshots of 16k points, 64 frames' clouds
    _no_temporaries(tmp_path)


def test_comparison_recording_side_by_side(sim2d, tmp_path: Path) -> None:
    path = tmp_path / "cmp.rrd"
    rec = ComparisonRecorder(path, recording_id="cmp-1", sequence=sim2d, labels=["icp", "identity"])
    sinks = {label: rec.sink(label) for label in ("icp", "identity")}
    lists = {label: ListSink() for label in sinks}
    for label in ("icp", "identity"):
        run(sim2d, RunConfig(method=label), sink=MultiSink([lists[label], sinks[label]]))
        assert rec.closed == (label == "identity")  # closes after the last expected result
    s = read_recording(path)
    assert set(s.runs) == {"icp", "identity"}
    assert {"world/icp/frames/frame_0", "world/identity/frames/frame_0", "metrics/icp/ate"} <= set(s.entity_paths)
    assert (s.runs["icp"].label, s.runs["identity"].label) == ("icp", "identity")
    _assert_last_poses(s.runs["icp"], lists["icp"], unit_scale=1100.0)
    _assert_last_poses(s.runs["identity"], lists["identity"], unit_scale=1100.0)
    # panels side by side: the second is shifted along +x by more than the ground-truth map's width
    gt_map = np.concatenate([f @ p[:2, :2].T + p[:2, 2] for f, p in zip(sim2d.frames, sim2d.poses, strict=True)])
    width = gt_map[:, 0].max() - gt_map[:, 0].min()
    shift = s.runs["identity"].offset - s.runs["icp"].offset
    assert shift[0] > width and shift[1] == 0 and shift[2] == 0
    _no_temporaries(tmp_path)


def test_cli_sink_and_partial_runs(sim2d, tmp_path: Path) -> None:
    # the CLI's sink as a context manager: a run cut short still leaves a complete file
    path = tmp_path / "cut.rrd"
    events = ListSink()
    run(sim2d, RunConfig(method="icp"), sink=events)
    with cli_sink(path, sim2d, "icp", "run-7") as rrd:
        for ev in events.events[:3]:  # the start and the first two iterations only
            rrd.emit(ev)
        assert not path.exists()  # nothing half-written is visible
    assert [e.kind for e in events.events[:3]] == ["start", "iteration", "iteration"]
    s = read_recording(path)
    assert s.recording_id == "run-7" and s.runs["icp"].iterations == [10, 20]
    # discarded recordings leave nothing behind
    other = RerunRecorder(tmp_path / "gone.rrd", recording_id="x", sequence=sim2d)
    other.emit(events.events[0])
    assert other.close(discard=True) is None
    # after the fact, from stored (JSON) events: the same poses as live
    stored = [ev.model_dump_json() for ev in events.events]
    stored.append('{"kind": "status", "status": "succeeded"}')  # job-log entries that are not progress
    write_recording(tmp_path / "stored.rrd", recording_id="run-8", sequence=sim2d, runs={"icp": stored})
    again = read_recording(tmp_path / "stored.rrd").runs["icp"]
    assert again.iterations == [10, 20, 30, 40, 50, 60, 64]
    _assert_last_poses(again, events, unit_scale=1100.0)
    _no_temporaries(tmp_path)


def test_the_recorder_does_not_import_viser() -> None:
    import subprocess
    import sys

    code = "import sys, app.rrd, app.viewer.scene; print(sorted({'viser', 'torch'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"


def test_an_unknown_event_kind_is_skipped_not_taken_for_an_iteration(sim2d, tmp_path: Path) -> None:
    """A kind without a reducer (a newer producer's) leaves the recording as it was."""

    class Note:
        kind = "note"
        iteration = 5  # an iteration-like field must not put it on the timeline
        ate = 123.0

    events = ListSink()
    run(sim2d, RunConfig(method="icp"), sink=events)
    path = tmp_path / "note.rrd"
    with RerunRecorder(path, recording_id="n", sequence=sim2d, label="icp", autoclose=False) as rec:
        for i, ev in enumerate(events.events):
            rec.emit(ev)
            if i == 1:
                rec.emit(Note())
    assert rec.failed is None
    r = read_recording(path).runs["icp"]
    assert r.iterations == [10, 20, 30, 40, 50, 60, 64] and 5 not in r.scalars["ate"][0]
    _assert_last_poses(r, events, unit_scale=1100.0)
