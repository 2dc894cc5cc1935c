"""The command line's early checks and what it says (issue 31's list)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from strep_cli import main
from strep_core.config import RunConfig
from strep_core.events import ListSink
from strep_core.runner import run
from strep_core.samples import load_sample

ROOT = Path(__file__).resolve().parents[1]


def _never(monkeypatch: pytest.MonkeyPatch) -> None:
    import strep_core.runner

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the run started")

    monkeypatch.setattr(strep_core.runner, "run_input", never)
    monkeypatch.setattr(strep_core.runner, "load_input", never)


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("strep ")


def test_an_unknown_option_prints_the_commands_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run", "sample:sim2d-small", "--bogus"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: strep run ") and "unrecognized arguments: --bogus" in err


def test_an_unknown_method_fails_before_loading(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    _never(monkeypatch)
    assert main(["run", "sample:sim2d-small", "--method", "foo", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown method 'foo'" in err and "loading" not in err


def test_cuda_without_a_gpu_fails_before_the_warm_start(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    _never(monkeypatch)
    assert main(["run", "sample:sim2d-small", "--device", "cuda", "--out", str(tmp_path / "o")]) == 2
    assert "device 'cuda' asked for, but torch sees no CUDA device" in capsys.readouterr().err


def test_rrd_into_a_missing_folder_is_an_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    _never(monkeypatch)
    target = tmp_path / "missing" / "run.rrd"
    assert main(["run", "sample:sim2d-small", "--out", str(tmp_path / "o"), "--rrd", str(target)]) == 2
    assert f"--rrd {target}: the folder {target.parent} does not exist" in capsys.readouterr().err
    assert not target.parent.exists()


@pytest.mark.parametrize(
    ("method", "said"), [("icp", "registering (12 frames)"), ("multiway", "registering (24 steps (each frame's ICP")]
)
def test_classical_runs_say_what_their_iterations_count(
    method: str, said: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    argv = ["run", "sample:sim2d-small", "--method", method, "--frames", "0:12", "--out", str(tmp_path)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert said in err and "iterations" not in err
    assert json.loads((tmp_path / "metrics.json").read_text())["iteration_unit"] != "iterations"


def test_methods_do_not_claim_the_occupancy_term(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    assert "Chamfer + occupancy" not in out
    assert RunConfig().loss.occupancy_weight == 0.0  # why: off by default


def test_the_warm_start_reports_its_progress(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """The pose graph under a learned method ran under a null sink: minutes without a word on a whole log."""
    sink = ListSink()
    run(load_sample("sim2d-small"), RunConfig.build(method="strep", frames="0:24", optim={"iterations": 0}), sink=sink)
    warm = [e for e in sink.events if e.kind == "stage" and e.stage == "init:multiway" and e.done is not None]
    assert len(warm) >= 2 and warm[-1].done == warm[-1].total == 48
    assert [e.done for e in warm] == sorted(e.done for e in warm)
    argv = ["run", "sample:sim2d-small", "--frames", "0:24", "--iterations", "0", "--out", str(tmp_path)]
    assert main(argv) == 0
    assert "warm start (multiway): 48/48 steps" in capsys.readouterr().err


def test_serve_on_a_busy_data_dir_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from app.server import serve
    from app.services import _lock_data_dir

    held = _lock_data_dir(tmp_path)
    try:
        assert serve(data_dir=tmp_path, port=0) == 2
    finally:
        held.close()
    err = capsys.readouterr().err
    assert err == f"strep serve: another STREP service is using {tmp_path}\n"


def test_the_service_data_dir_is_ignored_by_git() -> None:
    assert "strep-data/" in (ROOT / ".gitignore").read_text().splitlines()


def test_pytest_lanes_are_declared_and_ci_runs_every_test() -> None:
    """A fast default lane (no slow, browser or accuracy tests) and CI on all of them."""
    import tomllib

    pytest_cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    declared = {m.split(":")[0] for m in pytest_cfg["markers"]}
    assert {"slow", "browser", "accuracy"} <= declared
    assert "-m 'not slow and not browser and not accuracy'" in pytest_cfg["addopts"]
    assert 'python -m pytest -q -m ""' in (ROOT / ".ci" / "run").read_text()


def test_the_demo_methods_do_not_ship() -> None:
    assert not (ROOT / "app" / "demo.py").exists()
    assert (ROOT / "tests" / "plugins" / "strep_demo_methods.py").is_file()


def test_geometry_has_no_unused_compose() -> None:
    from strep_core import geometry

    assert not hasattr(geometry, "compose")  # poses compose with @; the helper was used by tests only


def test_readme_agrees_with_the_benchmarks_on_simulated_3d() -> None:
    readme = (ROOT / "README.md").read_text()
    row = next(line for line in readme.splitlines() if line.startswith("| simulated 3D, 10 walks"))
    assert "0.199" in row and "0.149" in row and "0.352" not in readme and "0.368" not in row
    assert "../shared/data/carmen/intel-corrected.log.gz" in readme
