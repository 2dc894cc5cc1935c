"""The strep command line, driven as a user would (in-process, through `main`)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from strep_core.cli import main
from strep_core.io.poses import read_tum


def test_run_identity_on_a_sample_writes_every_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    assert main(["run", "sample:sim2d-small", "--method", "identity", "--out", str(out), "--frames", "4:20:2"]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("identity on sim2d-small: 8 frames, ATE ")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "identity" and metrics["frames"] == 8 and metrics["ate"] > 1.0
    assert {"ate", "point_l2", "wall_seconds", "frames", "method"} <= metrics.keys()
    config = json.loads((out / "config.json").read_text())
    assert config["method"] == "identity" and config["frames"] == "4:20:2"
    traj = read_tum(out / "trajectory.tum")
    # the index column is each frame's index in the input file
    assert traj.stamps.tolist() == [4, 6, 8, 10, 12, 14, 16, 18]
    header = (out / "map.ply").read_bytes()[:200]
    assert b"element vertex 2048" in header  # 8 frames x 256 points


def test_config_file_and_set_overrides(tmp_path: Path) -> None:
    cfg = tmp_path / "base.json"
    cfg.write_text(json.dumps({"method": "identity", "seed": 5, "loss": {"window": 4}}))
    out = tmp_path / "run"
    assert main(["run", "sample:sim2d-small", "--config", str(cfg), "--set", "loss.window=3", "--out", str(out)]) == 0
    saved = json.loads((out / "config.json").read_text())
    assert saved["seed"] == 5 and saved["loss"]["window"] == 3 and saved["method"] == "identity"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["run", "does-not-exist.npz"], "no such file or folder"),
        (["run", "sample:nope"], "unknown sample 'nope'; known samples: sim2d-small"),
        (["run", "sample:sim2d-small", "--method", "magic"], "unknown method 'magic'"),
        (["run", "sample:sim2d-small", "--set", "optim.iterations=-3"], "optim.iterations: Input should be"),
        (["run", "sample:sim2d-small", "--set", "nonsense"], "expected KEY=VALUE"),
        (["run", "sample:sim2d-small", "--frames", "3:4"], "keeps 1 of 64 frames"),
        (["run", "sample:sim2d-small", "--freeze"], "--freeze needs --from-model"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("strep: error: ") and message in err


def test_malformed_file_is_reported_without_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"PK\x03\x04 this is not a zip")
    proc = subprocess.run(
        [sys.executable, "-m", "strep_core.cli", "run", str(bad), "--method", "identity", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and "broken.npz" in proc.stderr


def test_generate_samples_methods_info(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["generate", "2d", "--out", str(tmp_path), "--seed", "7", "--frames", "12"]) == 0
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    capsys.readouterr()
    assert main(["info", str(files[0])]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 12 and info["dims"] == 2 and info["has_ground_truth"] is True
    assert main(["samples"]) == 0
    assert "sample:sim3d-room" in capsys.readouterr().out
    assert main(["methods"]) == 0
    listed = capsys.readouterr().out
    assert all(m in listed for m in ("identity", "icp", "multiway", "kiss"))
    assert main(["generate", "3d", "--out", str(tmp_path / "dm"), "--format", "deepmapping"]) == 2


def test_generate_deepmapping_reads_back(tmp_path: Path) -> None:
    from strep_core.io import load_sequence

    assert main(["generate", "2d", "--out", str(tmp_path / "dm"), "--frames", "10", "--format", "deepmapping"]) == 0
    seq = load_sequence(tmp_path / "dm")
    assert len(seq) == 10 and seq.unit == "px" and seq.poses is not None
    assert np.isfinite(seq.frames[0]).all()
