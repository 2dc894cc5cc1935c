"""Settings chosen from the data (`strep_core.profiles`): the probe, the overlay, config.json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from strep_core import profiles
from strep_core.config import RunConfig
from strep_core.errors import ConfigError
from strep_core.resolve import resolve
from strep_core.runner import run


@pytest.fixture(scope="module")
def intel(shared_data: Path):
    from strep_core.io.carmen import read_carmen

    return read_carmen(shared_data / "carmen" / "intel-corrected.log.gz", frames="0:100")


def test_the_probe_picks_the_laser_keyframe_profile_for_a_carmen_log(intel) -> None:
    assert intel.meta["sensor"] == {"kind": "laser", "planar": True, "fov_deg": 180.0}
    found = profiles.probe(intel)
    assert found.profile == "laser-keyframes", found.reason
    # intel[0:100] turns by about 30 degrees between keyframes and steps about half its scale
    assert max(found.measures["turn_deg"]) > 25
    assert found.measures["pairs"] == profiles.PROBE_PAIRS
    assert "largest turn" in found.reason


def test_the_probe_picks_the_turning_camera_profile_for_a_simulated_walk() -> None:
    from strep_core.sim.depth3d import simulate_3d

    seq = simulate_3d(2000, frames=16)
    found = profiles.probe(seq)
    assert found.profile == "depth-turning", found.reason
    assert max(found.measures["turn_deg"]) >= 25  # the walk turns by 30 degrees in place
    cfg = resolve(RunConfig(method="icp"), seq).config
    assert cfg.profile == "depth-turning" and cfg.profile_reason.startswith("probe: ")
    assert cfg.classical.icp.yaw_axis == (0.0, -1.0, 0.0)  # the camera's own vertical axis (OpenCV)
    assert cfg.classical.icp.yaw_search == 30.0 and cfg.classical.icp.local_map_frames == 1


def test_the_probe_picks_the_dense_laser_profile_for_a_simulated_2d_lidar() -> None:
    from strep_core.sim.lidar2d import simulate_2d

    found = profiles.probe(simulate_2d(1000, frames=96, map_seed=0))
    assert found.profile == "laser-dense", found.reason
    assert max(found.measures["turn_deg"]) < profiles.KEYFRAME_TURN


def test_a_named_profile_skips_the_probe_and_given_fields_keep_their_values(intel) -> None:
    cfg = RunConfig.model_validate(
        {"method": "icp", "profile": "depth-turning", "classical": {"icp": {"yaw_search": 10.0}}}
    )
    out = resolve(cfg, intel).config
    assert out.profile == "depth-turning" and out.profile_reason == "given"
    assert out.classical.icp.yaw_search == 10.0  # given: kept
    assert out.classical.icp.yaw_step == 30.0  # left out: the profile's
    assert out.classical.icp.scales == [1.0, 0.5, 0.25]  # a field beside a given one in its sub-section
    plain = resolve(RunConfig(method="icp", profile="none"), intel).config
    default = RunConfig().classical
    assert (plain.classical.icp.degeneracy, plain.classical.icp.scales) == (default.icp.degeneracy, default.icp.scales)
    assert plain.classical.icp.motion_prior == default.icp.motion_prior and plain.loss == RunConfig().loss
    with pytest.raises(ConfigError):
        RunConfig.build(profile="laser-sparse")
    from typing import get_args

    from strep_core.config import ProfileName

    assert set(get_args(ProfileName)) == {"auto", *profiles.PROFILE_NAMES}  # one list of names


def test_a_saved_config_keeps_its_settings_whatever_the_probe_says(intel) -> None:
    cfg = resolve(RunConfig(method="icp"), intel).config
    saved = RunConfig.model_validate(json.loads(cfg.to_json()))
    # a saved config sets every field: applying its profile again changes nothing
    assert resolve(saved, intel).config == saved
    assert saved.profile == "laser-keyframes" and "probe" in (saved.profile_reason or "")


def test_a_config_json_from_the_benchmark_reruns_to_the_same_ate(shared_data: Path, tmp_path: Path) -> None:
    """A 7-Scenes row (reader option stride 8, frames 0:16): its recorded input and config
    reproduce its ATE through the same path as `strep run INPUT --config config.json`."""
    from strep_bench.cases import _sevenscenes, run_case
    from strep_core.runner import run_input

    case = next(c for c in _sevenscenes(shared_data, quick=True) if c.name == "7scenes[0:16]")
    (row,) = run_case(case, ["icp"], quick=True)
    assert row["status"] == "ok" and row["profile"] == "depth-handheld"
    assert row["config"]["data"]["stride"] == 8 and row["config"]["frames"] == "0:16"
    path = tmp_path / "config.json"
    path.write_text(json.dumps(row["config"]))
    again = run_input(row["input"], RunConfig.load(path), out_dir=tmp_path / "out")
    assert again.metrics["frames"] == 16
    assert again.metrics["ate"] == pytest.approx(row["ate"], rel=1e-6, abs=1e-9)
    written = json.loads((tmp_path / "out" / "config.json").read_text())
    assert written["profile"] == "depth-handheld" and written["data"]["stride"] == 8


def test_run_records_the_profile_in_metrics_and_config(intel) -> None:
    res = run(intel.select("0:6"), RunConfig(method="identity"))
    assert res.metrics["profile"] == res.config.profile
    assert res.config.profile_reason


def test_a_generated_walk_keeps_its_sensor_through_npz(tmp_path: Path) -> None:
    """`strep generate 3d` writes the camera's vertical axis into the .npz: the probe of the file
    read back picks the turning-camera profile as it does in memory."""
    from strep_core.io.npz import read_npz, write_npz
    from strep_core.sim.depth3d import simulate_3d

    write_npz(simulate_3d(2001, frames=16), tmp_path / "walk.npz")
    seq = read_npz(tmp_path / "walk.npz")
    assert seq.meta["sensor"] == {"kind": "depth", "vertical_axis": [0.0, -1.0, 0.0]}
    assert profiles.probe(seq).profile == "depth-turning"


def test_strep_run_takes_a_profile_and_config_json_records_it(tmp_path: Path) -> None:
    from strep_cli import main

    out = tmp_path / "run"
    argv = ["run", "sample:sim2d-small", "--method", "icp", "--frames", "0:8", "--out", str(out), "--quiet"]
    assert main([*argv, "--profile", "laser-keyframes"]) == 0
    saved = json.loads((out / "config.json").read_text())
    assert saved["profile"] == "laser-keyframes" and saved["profile_reason"] == "given"
    assert saved["classical"]["scanmatch"]["consecutive"] == "on" and saved["frames"] == "0:8"
    assert json.loads((out / "metrics.json").read_text())["profile"] == "laser-keyframes"
    assert main([*argv]) == 0  # auto: the probe chooses and says why
    saved = json.loads((out / "config.json").read_text())
    assert saved["profile"] in profiles.PROFILE_NAMES and saved["profile_reason"].startswith("probe: ")


def test_laser_keyframes_penalises_corrections_along_weak_directions() -> None:
    """The learned methods on CARMEN keyframes hold corridor slides (docs/design/warm-start.md)."""
    assert profiles.PROFILES["laser-keyframes"]["loss"]["weak_weight"] > 0
    assert RunConfig().loss.weak_weight == 0  # other data: unchanged
