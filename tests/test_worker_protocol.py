"""What a job's worker hands the service: the scene file it writes once, and the typed messages
on its pipe (`app.services.scenes`, `app.services.protocol`)."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from app.services.protocol import DoneMessage, EventMessage, JobSpec, PidMessage, parse_message
from app.services.scenes import read_scene, write_scene
from strep_core.runner import load_input


def test_the_scene_reads_back_as_the_worker_selected_it(tmp_path: Path) -> None:
    seq = load_input("sample:sim2d-small", frames="3:40:4")
    rng = np.random.default_rng(0)
    seq.colors = [rng.integers(0, 255, (len(f), 3), dtype=np.uint8) for f in seq.frames]
    path = write_scene(seq, tmp_path / "job" / "scene.npz")
    assert sorted(p.name for p in path.parent.iterdir()) == ["scene.npz"]  # no temporary left
    back = read_scene(path)
    assert (back.name, back.unit, back.dim, len(back)) == (seq.name, seq.unit, 2, 10)
    np.testing.assert_array_equal(back.indices, np.arange(3, 40, 4))
    assert seq.poses is not None and back.poses is not None
    np.testing.assert_array_equal(back.poses, seq.poses)
    np.testing.assert_array_equal(back.origins, seq.origins)
    for a, b, ca, cb in zip(seq.frames, back.frames, seq.colors, back.colors or [], strict=True):
        np.testing.assert_allclose(b, a, atol=1e-4 * np.abs(a).max())  # float32 points
        np.testing.assert_array_equal(cb, ca)
    with pytest.raises(FileNotFoundError):
        read_scene(tmp_path / "missing.npz")


def test_messages_cross_a_pipe_typed() -> None:
    recv, send = multiprocessing.Pipe(duplex=False)
    sent = [
        PidMessage(pid=12),
        EventMessage(event_kind="stage", data='{"kind": "stage", "stage": "load", "elapsed": 0.0}', emitted=1.5),
        DoneMessage(status="succeeded", metrics={"ate": 0.1}, files=["map.ply"]),
    ]
    for message in sent:
        send.send(message)
    assert [parse_message(recv.recv()) for _ in sent] == sent
    assert parse_message({"kind": "done", "status": "cancelled", "error": "cancelled"}).files == []
    with pytest.raises(ValidationError):
        parse_message(("done", "succeeded", None, None, []))  # the old untyped tuples are refused
    with pytest.raises(ValidationError):
        parse_message({"kind": "done", "status": "finished"})


def test_a_job_spec_is_checked() -> None:
    base = {
        "job_id": "job_1",
        "source": "sample:sim2d-small",
        "config": "{}",
        "scene_path": "s.npz",
        "tmp_dir": "t",
        "out_dir": "o",
        "threads": 1,
        "max_extract_bytes": 1 << 20,
    }
    assert JobSpec.model_validate(base).plugins == []
    with pytest.raises(ValidationError):
        JobSpec.model_validate({**base, "threads": 0})
    with pytest.raises(ValidationError):
        JobSpec.model_validate({k: v for k, v in base.items() if k != "scene_path"})
