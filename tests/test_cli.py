"""The strep command line, driven as a user would (in-process, through `main`)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from strep_cli import main
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
        [sys.executable, "-m", "strep_cli", "run", str(bad), "--method", "identity", "--out", str(tmp_path)],
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


# ---- issue 18: the newcomer's command line ------------------------------------------------------


def _cli(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The command in a fresh process, stderr a pipe (not a terminal), as a script would run it."""
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(
        [sys.executable, "-m", "strep_cli", *argv], capture_output=True, text=True, check=False, cwd=cwd, env=env
    )


def _cloud(path: Path, n: int = 300) -> Path:
    from strep_core.io.writers import write_ply

    write_ply(path, np.random.default_rng(0).uniform(0, 1, (n, 3)), None)
    return path


def test_one_point_cloud_is_described_by_info_and_refused_by_run_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: `strep run scan.ply` said "unknown format"."""
    scan = _cloud(tmp_path / "scan.ply")
    assert main(["info", str(scan)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["frames"], info["dims"], info["points"]) == (1, 3, 300)
    assert main(["run", str(scan), "--quiet", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "one frame" in err and "folder of PLY/PCD frames" in err and "npz (.npz)" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("frames/a.ply", b"hello, I am text\n", "not a PLY file"),  # before: Open3D's "RPly: Wrong magic number"
        ("notes.npz", b"hello, I am text\nand more text\n", "not a readable .npz file"),  # before: allow_pickle
        ("broken.tar", b"garbage" * 100, "not a readable tar archive"),  # before: five lines
    ],
)
def test_a_file_that_is_not_what_its_name_says_is_one_line(
    tmp_path: Path, name: str, content: bytes, message: str
) -> None:
    path = tmp_path / name
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(content)
    if name.startswith("frames/"):
        (tmp_path / "frames" / "b.ply").write_bytes(content)
    source = str(path.parent if name.startswith("frames/") else path)
    proc = _cli("run", source, "--quiet", "--method", "identity", "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("strep: error: ") and message in proc.stderr
    assert "RPly" not in proc.stderr and "allow_pickle" not in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    ("flag", "make", "message"), [("--out", "file", "is a file"), ("--rrd", "folder", "is a folder")]
)
def test_output_paths_are_checked_before_the_run(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    flag: str,
    make: str,
    message: str,
) -> None:
    """Before: `--out` naming an existing file failed only after the whole run."""
    import strep_core.runner

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the run started")

    monkeypatch.setattr(strep_core.runner, "run_input", never)
    monkeypatch.setattr(strep_core.runner, "load_input", never)
    taken = tmp_path / "taken"
    if make == "file":
        taken.write_text("mine")
    else:
        taken.mkdir()
    extra = ["--out", str(taken)] if flag == "--out" else ["--out", str(tmp_path / "o"), "--rrd", str(taken)]
    assert main(["run", "sample:sim2d-small", "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{flag} {taken}: {message}" in err


def test_out_below_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "f").write_text("")
    assert (
        main(["run", "sample:sim2d-small", "--quiet", "--method", "identity", "--out", str(tmp_path / "f" / "x")]) == 2
    )
    assert "is a file, not a folder" in capsys.readouterr().err


def test_progress_is_one_line_per_stage_into_a_file(tmp_path: Path) -> None:
    """Before: with stderr to a file only the final line appeared; nothing during the warm start."""
    out = tmp_path / "run"
    proc = _cli(
        "run", "sample:sim2d-small", "--frames", "0:12", "--iterations", "4", "--out", str(out), cwd=tmp_path
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    stages = [
        "strep: loading the sequence ...",
        "strep: warm start (multiway) ...",
        "strep: warm start (multiway): 10/24 steps",  # a line every tenth done (once per event here)
        "strep: warm start (multiway): 20/24 steps",
        "strep: warm start (multiway): 24/24 steps",
        "strep: starting poses: ATE ",
        "strep: optimising (4 iterations) ...",
        "strep: registered: ATE ",
        "strep: writing files ...",
    ]
    assert len(lines) == len(stages) and all(line.startswith(s) for line, s in zip(lines, stages, strict=True)), lines
    assert proc.stdout.startswith("strep on sim2d-small: 12 frames")
    quiet = _cli("run", "sample:sim2d-small", "--method", "identity", "--quiet", "--out", str(out), cwd=tmp_path)
    assert quiet.returncode == 0 and quiet.stderr == ""


def test_serve_takes_a_viewer_port(monkeypatch: pytest.MonkeyPatch) -> None:
    import app.server

    seen: dict[str, object] = {}
    monkeypatch.setattr(app.server, "serve", lambda **kw: seen.update(kw) or 0)
    assert main(["serve", "--port", "0", "--viewer-port", "0"]) == 0
    assert seen == {"host": None, "port": 0, "data_dir": None, "viewer_port": 0}


def test_readme_synopsis_matches_the_parser() -> None:
    """Every option the README's synopsis names exists on its command, and the run and serve
    options a newcomer needs are named there."""
    from strep_cli import make_parser

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = readme.split("## The command line", 1)[1].split("```text", 1)[1].split("```", 1)[0]
    parser = make_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command").choices  # type: ignore[attr-defined]
    command = None
    named: dict[str, set[str]] = {}
    for line in block.splitlines():
        if line.startswith("strep "):
            command = line.split()[1]
        if command is None:
            continue
        for option in re.findall(r"\[(--[a-z-]+)", line) + re.findall(r"(?<![\w-])(--[a-z-]+)", line):
            named.setdefault(command, set()).add(option)
    for command, options in named.items():
        known = {s for a in subparsers[command]._actions for s in a.option_strings}
        assert options <= known, (command, options - known)
    assert {"--init", "--threads", "--quiet", "--progress", "--start", "--rrd"} <= named["run"]
    assert "ground_truth" in block and "--viewer-port" in named["serve"]


def test_progress_bar_while_optimising(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--progress (or a terminal): the stage lines, and a tqdm bar over the iterations."""
    args = ["run", "sample:sim2d-small", "--frames", "0:12", "--iterations", "4", "--progress"]
    assert main([*args, "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    assert "strep: warm start (multiway) ..." in err and "strep: optimising (4 iterations) ..." in err
    assert "4/4" in err and ("it/s" in err or "s/it" in err), err  # the bar
