"""Readers and writers: real data from ../shared/data, round trips, and malformed inputs.

Bounds on real data were measured once and are asserted with a margin:

* v1_pose0 placed by gt_pose.mat: median NN distance between consecutive frames 0.91 px
  (median over pairs), worst pair 2.26 px.
* intel placed by its corrected poses: 0.030 m (median over pairs), 90th percentile 0.054 m;
  aces 0.045 m and 0.063 m. Mirroring the beams (wrong angle convention) gives 0.45 m.
* 7-Scenes frames 0 vs 40 and 0 vs 60 (stride 4) placed by pose.txt: 0.010 m and 0.013 m;
  unplaced (identity) 0.073 m, placed with inverted poses 0.126 m.
* Stanford bunny placed by bun.conf: each scan 0.23 to 0.34 mm from the union of the others.
"""

from __future__ import annotations

import gzip
import itertools
import json
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from scipy.spatial import cKDTree

from strep_core import geometry as g
from strep_core.errors import ConfigError, FormatError, SequenceError
from strep_core.io import (
    FORMATS,
    detect_format,
    load_sequence,
    read_carmen,
    read_conf,
    read_depth_folder,
    read_folder,
    read_intrinsics,
    read_kitti,
    read_npz,
    read_tum,
    write_json,
    write_npz,
    write_ply,
    write_tum,
)
from strep_core.io.pcd import format_pcd
from strep_core.sequence import Sequence

# ---------------------------------------------------------------------------------------------
# helpers


def placed(seq: Sequence, poses: np.ndarray | None = None) -> list[np.ndarray]:
    """Every frame in world coordinates, placed by ``poses`` (default: the ground truth)."""
    poses = seq.poses if poses is None else poses
    assert poses is not None
    return [g.apply(p, f) for p, f in zip(poses, seq.frames, strict=True)]


def consecutive_medians(world: list[np.ndarray]) -> np.ndarray:
    """Median NN distance from frame i+1 to frame i, for every consecutive pair."""
    return np.array([np.median(cKDTree(a).query(b)[0]) for a, b in itertools.pairwise(world)])


def median_nn(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.median(cKDTree(a).query(b)[0]))


def random_poses_3d(rng: np.random.Generator, k: int) -> np.ndarray:
    q = rng.normal(size=(k, 4))
    poses = np.tile(np.eye(4), (k, 1, 1))
    poses[:, :3, :3] = g.quaternion_to_rotation(q)
    poses[:, :3, 3] = rng.uniform(-5, 5, size=(k, 3))
    return poses


# ---------------------------------------------------------------------------------------------
# DeepMapping (real data)


def test_v1_pose0_reads_256_frames_that_overlap_when_placed(v1_pose0: Sequence) -> None:
    seq = v1_pose0
    assert len(seq) == 256 and seq.dim == 2 and seq.unit == "px"
    assert all(f.shape == (256, 2) for f in seq.frames)
    assert seq.poses is not None and seq.poses.shape == (256, 3, 3)
    meds = consecutive_medians(placed(seq))
    assert np.median(meds) < 1.5  # measured 0.91 px
    assert meds.max() < 3.0  # measured 2.26 px


def test_load_sequence_tar_keeps_original_indices(shared_data: Path, v1_pose0: Sequence) -> None:
    seq = load_sequence(shared_data / "deepmapping_2d" / "v1_pose0.tar", frames="10:20:3")
    assert seq.indices.tolist() == [10, 13, 16, 19]
    np.testing.assert_allclose(seq.frames[1], v1_pose0.frames[13])
    assert seq.poses is not None and v1_pose0.poses is not None
    np.testing.assert_allclose(seq.poses, v1_pose0.poses[[10, 13, 16, 19]])


def test_tar_that_is_not_a_tar_raises_format_error(tmp_path: Path) -> None:
    bad = tmp_path / "seq.tar"
    bad.write_bytes(b"this is not a tar archive" * 40)
    with pytest.raises(FormatError, match=r"seq\.tar"):
        load_sequence(bad)


# ---------------------------------------------------------------------------------------------
# CARMEN


@pytest.fixture(scope="module")
def intel(shared_data: Path) -> Sequence:
    return read_carmen(shared_data / "carmen" / "intel-corrected.log.gz")


def test_intel_reads_910_scans_that_overlap_when_placed(intel: Sequence) -> None:
    assert len(intel) == 910 and intel.dim == 2 and intel.unit == "m"
    assert intel.poses is not None and intel.poses.shape == (910, 3, 3)
    assert all(3 <= len(f) <= 180 for f in intel.frames)
    # the log's maximum 81.83 m is beyond 80 m: the 80 m default applies
    assert intel.meta["max_range"] == 80.0
    assert max(np.linalg.norm(f, axis=1).max() for f in intel.frames) < 80.0
    # this "corrected" log repeats the corrected pose as odometry: no initial guess is given
    assert intel.initial_poses is None
    meds = consecutive_medians(placed(intel))
    assert np.median(meds) < 0.05  # measured 0.030 m
    assert np.percentile(meds, 90) < 0.08  # measured 0.054 m
    # the beam angle convention matters: mirrored beams do not overlap
    mirrored = [f * [1.0, -1.0] for f in intel.frames[:100]]
    wrong = consecutive_medians([g.apply(p, f) for p, f in zip(intel.poses[:100], mirrored, strict=True)])
    assert np.median(wrong) > 0.2  # measured 0.45 m


def test_aces_reads_440_scans_and_drops_its_50_m_sentinel(shared_data: Path) -> None:
    aces = read_carmen(shared_data / "carmen" / "aces-corrected.log.gz")
    assert len(aces) == 440 and aces.dim == 2
    assert aces.meta["max_range_rule"] == "sentinel" and aces.meta["max_range"] == 50.0
    assert max(np.linalg.norm(f, axis=1).max() for f in aces.frames) < 50.0
    meds = consecutive_medians(placed(aces))
    assert np.median(meds) < 0.07  # measured 0.045 m
    assert np.percentile(meds, 90) < 0.09  # measured 0.063 m


def test_acapulco_drops_its_51_15_m_code_below_its_largest_reading(shared_data: Path) -> None:
    """The no-return code need not be the largest reading: acapulco's largest is 51.25 m (a
    few), 51.15 m makes 6 % of its readings and 50.0 m (another code) 0.5 %."""
    seq = read_carmen(shared_data / "carmen" / "acapulco-corrected.log.gz", frames="440:450")
    assert seq.meta["max_range_rule"] == "sentinel" and seq.meta["max_range"] == 50.0
    assert max(np.linalg.norm(f, axis=1).max() for f in seq.frames) < 50.0


def test_carmen_code_repeated_below_a_stray_maximum(tmp_path: Path) -> None:
    lines = [_flaser([1.0 + 0.1 * i, 2.0 + 0.1 * i, 8.0, 8.0, 3.0], (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) for i in range(9)]
    lines.append(_flaser([1.0, 2.0, 8.2, 8.0, 3.0], (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)))
    log = tmp_path / "codes.log.gz"
    log.write_bytes(gzip.compress(("\n".join(lines) + "\n").encode()))
    seq = read_carmen(log)
    # 8.0 repeats within 5 % of the largest reading (8.2, once): both are dropped
    assert seq.meta["max_range"] == 8.0 and seq.meta["max_range_rule"] == "sentinel"
    assert all(len(f) == 3 for f in seq.frames)


def test_carmen_selection_keeps_original_indices(shared_data: Path, intel: Sequence) -> None:
    sel = load_sequence(shared_data / "carmen" / "intel-corrected.log.gz", frames="300:400:2")
    assert sel.indices.tolist() == list(range(300, 400, 2))
    assert sel.poses is not None and intel.poses is not None
    np.testing.assert_array_equal(sel.poses, intel.poses[300:400:2])
    np.testing.assert_array_equal(sel.frames[5], intel.frames[310])


def test_carmen_max_range_option(shared_data: Path) -> None:
    seq = load_sequence(shared_data / "carmen" / "intel-corrected.log.gz", frames="0:50", max_range=5.0)
    assert seq.meta["max_range_rule"] == "max_range"
    assert max(np.linalg.norm(f, axis=1).max() for f in seq.frames) < 5.0


def _flaser(ranges: list[float], pose: tuple[float, float, float], odom: tuple[float, float, float]) -> str:
    nums = [len(ranges), *ranges, *pose, *odom]
    return "FLASER " + " ".join(str(v) for v in nums) + " 12.5 host 12.5"


def test_carmen_beam_geometry_invalid_ranges_and_odometry(tmp_path: Path) -> None:
    lines = [
        "# a comment",
        "PARAM robot_use_laser on nohost 0",
        "ODOM 0 0 0 0 0 0 0.1 host 0.1",
        _flaser([1.0, 2.0, 1.0, 0.0, 8.0], (0.0, 0.0, 0.0), (0.1, 0.0, 0.0)),
        _flaser([1.0, 1.0, 1.0, 8.0, float("nan")], (1.0, 2.0, np.pi / 2), (1.1, 2.0, 1.5)),
        _flaser([1.0, 1.0, 3.0, 1.0, 8.0], (2.0, 2.0, 0.0), (2.1, 2.0, 0.0)),
    ]
    log = tmp_path / "tiny.log.gz"
    log.write_bytes(gzip.compress(("\n".join(lines) + "\n").encode()))
    seq = read_carmen(log)
    # 5 beams from -90 to +90 degrees; 0, nan and the repeated maximum 8.0 are dropped
    s = np.sqrt(0.5)
    np.testing.assert_allclose(seq.frames[0], [[0, -1], [2 * s, -2 * s], [1, 0]], atol=1e-12)
    assert len(seq.frames[1]) == 3 and len(seq.frames[2]) == 4
    assert seq.meta["max_range"] == 8.0 and seq.meta["max_range_rule"] == "sentinel"
    assert seq.initial_poses is not None  # odometry differs from the corrected poses here
    np.testing.assert_allclose(g.se2_to_xytheta(seq.initial_poses)[1], [1.1, 2.0, 1.5])
    np.testing.assert_allclose(g.se2_to_xytheta(seq.poses)[1], [1.0, 2.0, np.pi / 2])


def test_carmen_beam_step_is_the_formats_own(tmp_path: Path) -> None:
    """180 beams step 1 degree from -90 (the last at +89, as CARMEN reads them), 181 span 180
    degrees exactly, 360 step 0.5 degree; other counts span 180 degrees."""
    from strep_core.io.carmen import beam_step

    assert np.degrees([beam_step(180), beam_step(181), beam_step(360), beam_step(401)]) == pytest.approx(
        [1.0, 1.0, 0.5, 0.25]
    )
    assert beam_step(5) == pytest.approx(np.pi / 4)
    log = tmp_path / "sick.log.gz"
    line = _flaser(list(2.0 + 0.01 * np.arange(180)), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    log.write_bytes(gzip.compress((line + "\n" + line + "\n").encode()))
    pts = read_carmen(log, max_range=10.0).frames[0]
    bearing = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    assert bearing[0] == pytest.approx(-90.0) and bearing[-1] == pytest.approx(89.0)


@pytest.mark.parametrize(
    "content",
    [
        b"FLASER 180 1.0 2.0 3.0 0 0 0 0 0 0 1 host 1\n",  # too few numbers for 180 beams
        b"FLASER 3 1.0 x 1.0 0 0 0 0 0 0 1 host 1\n",  # a range that is not a number
        b"ODOM 0 0 0 0 0 0 1 host 1\n",  # no FLASER line
        b"\xff\xfe\x00binary\x00",  # not text
        gzip.compress(b"FLASER 3 1 1 1 0 0 0 0 0 0 1 h 1\n" * 5)[:-10],  # truncated gzip
    ],
    ids=["too-few-numbers", "not-a-number", "no-flaser", "binary", "truncated-gz"],
)
def test_malformed_carmen_raises_format_error(tmp_path: Path, content: bytes) -> None:
    log = tmp_path / "bad.log"
    log.write_bytes(content)
    with pytest.raises(FormatError, match=r"bad\.log"):
        load_sequence(log)


# ---------------------------------------------------------------------------------------------
# Depth image folders


@pytest.fixture(scope="module")
def scenes_window(shared_data: Path) -> Sequence:
    return load_sequence(shared_data / "7scenes", frames="0:64:4")


def test_7scenes_window_reads_with_indices_colours_and_poses(scenes_window: Sequence) -> None:
    seq = scenes_window
    assert len(seq) == 16 and seq.dim == 3 and seq.unit == "m"
    assert seq.indices.tolist() == list(range(0, 64, 4))
    assert seq.meta["intrinsics"] == [585.0, 585.0, 320.0, 240.0]
    for f in seq.frames:  # 640 x 480 at stride 4: at most 160 x 120 pixels, ~17k valid
        assert 15_000 < len(f) <= 160 * 120
        assert f[:, 2].min() > 0.3 and f[:, 2].max() < 5.0  # metres
    assert seq.colors is not None
    assert all(c.dtype == np.uint8 and c.shape == f.shape for c, f in zip(seq.colors, seq.frames, strict=True))
    assert seq.poses is not None and seq.poses.shape == (16, 4, 4)


def test_7scenes_frames_placed_by_reference_poses_are_coherent(scenes_window: Sequence) -> None:
    seq = scenes_window
    world = placed(seq)
    for j in (10, 15):  # frames 40 and 60 against frame 0
        d = median_nn(world[0], world[j])
        assert d < 0.02  # measured 0.010 m and 0.013 m
        assert median_nn(seq.frames[0], seq.frames[j]) > 3 * d  # unplaced: 0.073 m at frame 40
    inverted = placed(seq, g.inverse(seq.poses))
    assert median_nn(inverted[0], inverted[10]) > 0.05  # wrong direction: 0.126 m


def test_depth_stride_intrinsics_override_and_max_depth(shared_data: Path) -> None:
    folder = shared_data / "7scenes"
    base = read_depth_folder(folder, frames="0:2", stride=8)
    assert all(len(f) <= 80 * 60 for f in base.frames)
    wider = read_depth_folder(folder, frames="0:2", stride=8, intrinsics=(292.5, 292.5, 320.0, 240.0))
    np.testing.assert_allclose(wider.frames[0][:, :2], 2 * base.frames[0][:, :2])
    near = read_depth_folder(folder, frames="0:2", stride=8, max_depth=1.5)
    assert near.frames[0][:, 2].max() <= 1.5 and len(near.frames[0]) < len(base.frames[0])


def _write_depth(path: Path, depth_mm: np.ndarray) -> None:
    Image.fromarray(depth_mm.astype(np.uint16)).save(path)


def test_tum_layout_depth_folder_matches_poses_by_time_stamp(tmp_path: Path) -> None:
    (tmp_path / "depth").mkdir()
    stamps = [100.0, 100.5, 101.0]
    for i, s in enumerate(stamps):
        depth = np.full((24, 32), 1000 + 100 * i)
        depth[0, :] = 0  # invalid row
        _write_depth(tmp_path / "depth" / f"{s:.6f}.png", depth)
    (tmp_path / "intrinsics.json").write_text(json.dumps({"fx": 30.0, "fy": 30.0, "cx": 16.0, "cy": 12.0}))
    rng = np.random.default_rng(0)
    poses = random_poses_3d(rng, 5)
    gt_stamps = np.array([99.5, 100.001, 100.499, 101.01, 102.0])
    lines = [
        f"{t:.6f} " + " ".join(f"{v:.12g}" for v in [*p[:3, 3], *g.rotation_to_quaternion(p[:3, :3])])
        for t, p in zip(gt_stamps, poses, strict=True)
    ]
    (tmp_path / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    seq = load_sequence(tmp_path, frames="1:", stride=2)
    assert seq.indices.tolist() == [1, 2]
    assert all(len(f) == 11 * 16 for f in seq.frames)  # row 0 invalid; 12 x 16 sampled pixels
    np.testing.assert_allclose(seq.frames[0][:, 2], 1.1)
    assert seq.poses is not None
    np.testing.assert_allclose(seq.poses, poses[[2, 3]], atol=1e-9)


def _seven_scenes_copy(shared_data: Path, dest: Path, n: int = 2) -> Path:
    src = shared_data / "7scenes"
    (dest / "camera-intrinsics.txt").write_bytes((src / "camera-intrinsics.txt").read_bytes())
    for i in range(n):
        for kind in ("depth.png", "pose.txt"):
            name = f"frame-{i:06d}.{kind}"
            (dest / name).write_bytes((src / name).read_bytes())
    return dest


def test_depth_png_that_is_not_a_png_raises_format_error(shared_data: Path, tmp_path: Path) -> None:
    folder = _seven_scenes_copy(shared_data, tmp_path)
    (folder / "frame-000001.depth.png").write_bytes(b"\x89PNG but not really" * 10)
    with pytest.raises(FormatError, match=r"frame-000001\.depth\.png"):
        load_sequence(folder)


def test_8_bit_depth_png_raises_format_error(shared_data: Path, tmp_path: Path) -> None:
    folder = _seven_scenes_copy(shared_data, tmp_path)
    Image.fromarray(np.zeros((48, 64), np.uint8)).save(folder / "frame-000001.depth.png")
    with pytest.raises(FormatError, match="16-bit"):
        load_sequence(folder)


@pytest.mark.parametrize("content", ["fx fy cx cy\n", "585 0 320\n0 585\n", "-1 585 320 240\n", "\xff"], ids=str)
def test_garbage_intrinsics_raise_format_error(shared_data: Path, tmp_path: Path, content: str) -> None:
    folder = _seven_scenes_copy(shared_data, tmp_path)
    (folder / "camera-intrinsics.txt").write_text(content, encoding="latin-1")
    with pytest.raises(FormatError, match=r"camera-intrinsics\.txt"):
        load_sequence(folder)


def test_intrinsics_files(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text("525.0 526.0 319.5 239.5\n")
    assert read_intrinsics(tmp_path / "a.txt") == (525.0, 526.0, 319.5, 239.5)
    (tmp_path / "b.json").write_text(json.dumps({"K": [[500, 0, 320], [0, 501, 240], [0, 0, 1]]}))
    assert read_intrinsics(tmp_path / "b.json") == (500.0, 501.0, 320.0, 240.0)
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(FormatError, match=r"c\.json"):
        read_intrinsics(tmp_path / "c.json")


# ---------------------------------------------------------------------------------------------
# Stanford .conf


@pytest.fixture(scope="module")
def bunny(shared_data: Path) -> Sequence:
    return load_sequence(shared_data / "stanford_bunny")


def test_bunny_scans_placed_by_conf_lie_within_half_a_millimetre(bunny: Sequence) -> None:
    assert len(bunny) == 10 and bunny.dim == 3 and bunny.unit == "m"
    assert bunny.meta["files"][:2] == ["bun000.ply", "bun045.ply"]  # file order; 'camera' ignored
    assert all(30_000 < len(f) < 41_000 for f in bunny.frames)
    world = placed(bunny)
    for i in range(len(world)):
        others = np.concatenate([w for j, w in enumerate(world) if j != i])
        assert median_nn(others, world[i][::10]) < 0.5e-3  # measured 0.23 to 0.34 mm
    # the transposed convention (R(q) p + t) does not register the scans
    wrong = bunny.poses.copy()
    wrong[:, :3, :3] = np.swapaxes(wrong[:, :3, :3], 1, 2)
    assert median_nn(g.apply(wrong[0], bunny.frames[0]), g.apply(wrong[1], bunny.frames[1])[::10]) > 2e-3


def test_conf_selection_and_voxel(shared_data: Path, bunny: Sequence) -> None:
    seq = read_conf(shared_data / "stanford_bunny" / "bun.conf", frames="2:5", voxel=0.002)
    assert seq.indices.tolist() == [2, 3, 4]
    assert seq.poses is not None and bunny.poses is not None
    np.testing.assert_array_equal(seq.poses, bunny.poses[2:5])
    assert all(100 < len(f) < len(b) / 4 for f, b in zip(seq.frames, bunny.frames[2:5], strict=True))


def test_conf_with_missing_scan_or_bad_line_raises_format_error(tmp_path: Path) -> None:
    write_ply(tmp_path / "a.ply", np.random.default_rng(0).normal(size=(50, 3)))
    conf = tmp_path / "scans.conf"
    conf.write_text("camera 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\nbmesh missing.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"missing\.ply"):
        load_sequence(tmp_path)
    conf.write_text("bmesh a.ply 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"scans\.conf:2"):
        load_sequence(conf)


# ---------------------------------------------------------------------------------------------
# PLY / PCD folders and pose files


def test_folder_of_ply_with_colours_and_tum_poses_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    names = ["frame1.ply", "frame2.ply", "frame10.ply"]  # natural order: 1, 2, 10
    clouds = [rng.normal(size=(40 + i, 3)) for i in range(3)]
    colors = [rng.integers(0, 256, size=(40 + i, 3), dtype=np.uint8) for i in range(3)]
    for name, pts, col in zip(names, clouds, colors, strict=True):
        write_ply(tmp_path / name, pts, col)
    poses = random_poses_3d(rng, 3)
    write_tum(tmp_path / "poses.txt", poses)
    seq = load_sequence(tmp_path)
    assert seq.meta["format"] == "folder" and seq.meta["files"] == names
    for f, c, pts, col in zip(seq.frames, seq.colors, clouds, colors, strict=True):
        np.testing.assert_allclose(f, pts, rtol=1e-6, atol=1e-6)  # float32 on disk
        np.testing.assert_array_equal(c, col)
    np.testing.assert_allclose(seq.poses, poses, atol=1e-9)
    sub = read_folder(tmp_path, frames="1:")
    assert sub.indices.tolist() == [1, 2]
    np.testing.assert_allclose(sub.poses, poses[1:], atol=1e-9)


def test_folder_of_planar_pcd_stays_3d_with_kitti_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    for i in range(3):
        (tmp_path / f"{i:03d}.pcd").write_bytes(format_pcd(rng.normal(size=(30, 2))))
    poses = random_poses_3d(rng, 3)
    (tmp_path / "trajectory.kitti").write_text(
        "\n".join(" ".join(f"{v:.15g}" for v in p[:3].ravel()) for p in poses) + "\n"
    )
    seq = load_sequence(tmp_path)
    assert seq.dim == 3 and np.all(seq.frames[0][:, 2] == 0)
    assert seq.colors is None
    np.testing.assert_allclose(seq.poses, poses, atol=1e-12)


def test_truncated_pcd_raises_format_error(tmp_path: Path) -> None:
    data = format_pcd(np.random.default_rng(3).normal(size=(100, 3)))
    (tmp_path / "000.pcd").write_bytes(data)
    (tmp_path / "001.pcd").write_bytes(data[:-100])
    with pytest.raises(FormatError, match=r"001\.pcd"):
        load_sequence(tmp_path)


def test_kitti_line_with_11_numbers_raises_format_error(tmp_path: Path) -> None:
    bad = tmp_path / "poses.kitti"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"poses.kitti:2: .*12 numbers.* not 11"):
        read_kitti(bad)


def test_tum_line_with_7_numbers_raises_format_error(tmp_path: Path) -> None:
    bad = tmp_path / "traj.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"traj\.tum:2"):
        read_tum(bad)


@settings(max_examples=25, deadline=None)
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
    t=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
    index=st.integers(0, 10**6),
)
def test_tum_round_trip_3d(q: list[float], t: list[float], index: int) -> None:
    pose = np.eye(4)
    pose[:3, :3] = g.quaternion_to_rotation(np.array(q))
    pose[:3, 3] = t
    poses = np.stack([pose, np.eye(4)])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "traj.txt"
        write_tum(path, poses, np.array([index, index + 7]))
        stamps, back = read_tum(path)
    assert stamps.tolist() == [index, index + 7]
    # 12 significant digits on disk; rotations within 180 degrees +- 1e-8 lose ~sqrt(eps)
    # in geometry.rotation_to_quaternion (arccos-based angle), hence 1e-7 and not 1e-9
    np.testing.assert_allclose(back, poses, atol=1e-7)


@settings(max_examples=25, deadline=None)
@given(
    xytheta=st.lists(
        st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-np.pi, np.pi)), min_size=1, max_size=5
    )
)
def test_tum_round_trip_2d(xytheta: list[tuple[float, float, float]]) -> None:
    poses = g.se2_from_xytheta(np.array(xytheta))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "traj.tum"
        write_tum(path, poses, np.arange(len(poses)) * 3)
        stamps, back2 = read_tum(path, dim=2)
        _, back3 = read_tum(path)
    assert stamps.tolist() == [3 * i for i in range(len(poses))]
    np.testing.assert_allclose(back2, poses, atol=1e-8)
    np.testing.assert_allclose(back3, g.to_se3(poses), atol=1e-8)


def test_read_tum_dim_2_refuses_non_planar_poses(tmp_path: Path) -> None:
    write_tum(tmp_path / "t.txt", random_poses_3d(np.random.default_rng(4), 2))
    with pytest.raises(FormatError, match="not planar"):
        read_tum(tmp_path / "t.txt", dim=2)


# ---------------------------------------------------------------------------------------------
# Writers


def test_write_ply_reads_back_with_open3d(tmp_path: Path) -> None:
    from strep_core._open3d import o3d

    rng = np.random.default_rng(5)
    pts = rng.normal(size=(500, 3)) * 10
    col = rng.integers(0, 256, size=(500, 3), dtype=np.uint8)
    write_ply(tmp_path / "map.ply", pts, col)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "map.ply"))
    np.testing.assert_array_equal(np.asarray(cloud.points), pts.astype(np.float32))
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, col, atol=1e-6)
    flat = rng.normal(size=(20, 2))
    write_ply(tmp_path / "flat.ply", flat)
    back = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "flat.ply")).points)
    np.testing.assert_array_equal(back, np.c_[flat.astype(np.float32), np.zeros(20)])
    with pytest.raises(FormatError, match=r"bad\.ply"):
        write_ply(tmp_path / "bad.ply", np.zeros((5, 4)))


def test_write_json_converts_numpy_and_nan(tmp_path: Path) -> None:
    obj = {"ate": np.float32(1.5), "n": np.int64(3), "curve": np.array([1.0, np.nan]), "inf": float("inf"),
           "path": tmp_path, "ok": np.bool_(True), 7: (1, 2)}  # fmt: skip
    write_json(tmp_path / "metrics.json", obj)
    text = (tmp_path / "metrics.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"ate": 1.5, "n": 3, "curve": [1.0, None], "inf": None,
                                "path": str(tmp_path), "ok": True, "7": [1, 2]}  # fmt: skip
    with pytest.raises(FormatError, match="object"):
        write_json(tmp_path / "x.json", {"x": object()})


def test_writers_never_leave_half_written_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "metrics.json"
    write_json(target, {"v": 1})

    def boom(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    for write in (
        lambda: write_json(target, {"v": 2}),
        lambda: write_ply(target, np.zeros((3, 3))),
        lambda: write_tum(target, np.eye(3)[None].repeat(2, 0)),
    ):
        with pytest.raises(OSError, match="disk full"):
            write()
    assert json.loads(target.read_text()) == {"v": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]  # no temporary left


# ---------------------------------------------------------------------------------------------
# npz and load_sequence


def test_npz_round_trip(tmp_path: Path, v1_pose0: Sequence) -> None:
    seq = v1_pose0.select("0:20:5")
    write_npz(seq, tmp_path / "s.npz")
    back = load_sequence(tmp_path / "s.npz")
    assert back.unit == "px" and back.indices.tolist() == [0, 5, 10, 15]
    for a, b in zip(back.frames, seq.frames, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-4)  # float32 points
    np.testing.assert_array_equal(back.poses, seq.poses)


def test_npz_with_nan_raises_sequence_error(tmp_path: Path) -> None:
    frames = np.random.default_rng(6).normal(size=(3, 10, 2))
    frames[1, 4, 0] = np.nan
    np.savez(tmp_path / "nan.npz", frames=frames)
    with pytest.raises(SequenceError, match=r"nan\.npz"):
        read_npz(tmp_path / "nan.npz")


def _zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _npz_bytes(seq: Sequence, tmp: Path) -> bytes:
    write_npz(seq, tmp / "inner.npz")
    return (tmp / "inner.npz").read_bytes()


def test_zip_is_extracted_and_dispatched(tmp_path: Path, v1_pose0: Sequence) -> None:
    archive = _zip(tmp_path / "seq.zip", {"data/seq.npz": _npz_bytes(v1_pose0.select("0:8"), tmp_path)})
    seq = load_sequence(archive, frames="2:6")
    assert seq.indices.tolist() == [2, 3, 4, 5] and seq.meta["source"] == str(archive)
    ply_dir = tmp_path / "plys"
    ply_dir.mkdir()
    for i in range(3):
        write_ply(ply_dir / f"{i}.ply", np.random.default_rng(i).normal(size=(10, 3)))
    archive = _zip(tmp_path / "frames.zip", {f"scan/{i}.ply": (ply_dir / f"{i}.ply").read_bytes() for i in range(3)})
    assert len(load_sequence(archive)) == 3


def test_zip_with_parent_path_is_refused(tmp_path: Path) -> None:
    (tmp_path / "work").mkdir()
    archive = _zip(tmp_path / "work" / "evil.zip", {"ok.npz": b"x", "../evil": b"gotcha"})
    with pytest.raises(FormatError, match=r"unsafe entry '\.\./evil'"):
        load_sequence(archive)
    archive = _zip(tmp_path / "work" / "abs.zip", {"/etc/evil": b"gotcha"})
    with pytest.raises(FormatError, match="unsafe entry"):
        load_sequence(archive)
    assert not (tmp_path / "evil").exists()


def test_zip_inflating_beyond_the_limit_is_refused(tmp_path: Path) -> None:
    archive = _zip(tmp_path / "bomb.zip", {"big.npz": b"\0" * 1_000_000})
    assert archive.stat().st_size < 10_000
    with pytest.raises(FormatError, match="limit"):
        load_sequence(archive, max_extract_bytes=100_000)


def test_unknown_missing_and_bad_option_inputs(tmp_path: Path, shared_data: Path) -> None:
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(FormatError, match="unknown format; expected one of"):
        load_sequence(tmp_path / "notes.txt")
    with pytest.raises(FormatError, match="no such file"):
        load_sequence(tmp_path / "absent.npz")
    with pytest.raises(FormatError, match="unknown format"):
        load_sequence(tmp_path)  # a folder with nothing readable
    with pytest.raises(FormatError):
        load_sequence(_zip(tmp_path / "x.zip", {"readme.txt": b"hi"}))
    with pytest.raises(ConfigError, match="stride"):
        load_sequence(shared_data / "carmen" / "aces-corrected.log.gz", stride=2)


def test_formats_describe_every_dispatch(shared_data: Path) -> None:
    names = {f.name for f in FORMATS}
    assert names == {"npz", "deepmapping", "carmen", "conf", "depth", "folder", "zip"}
    assert all(f.extensions and f.description for f in FORMATS)
    assert detect_format(shared_data / "7scenes") == "depth"
    assert detect_format(shared_data / "stanford_bunny") == "conf"
    assert detect_format(shared_data / "carmen" / "intel-corrected.log.gz") == "carmen"


def test_a_new_format_is_its_reader_and_one_row_of_formats(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/design/extending.md: one row in `FORMATS` makes a reader detected, dispatched (with its
    options checked), listed and, for a one-file format, accepted as an upload."""
    import strep_core.io as io
    from app.services.uploads import UPLOAD_FORMATS

    calls = []

    def read_xyz(path: Path, *, frames: str | None = None, budget: object = None, scale: float = 1.0) -> Sequence:
        calls.append((path.name, frames, scale))
        pts = np.loadtxt(path).reshape(4, -1, 2) * scale
        return Sequence(frames=list(pts), name=path.stem, unit="px")

    row = io.FormatInfo("xyz", (".xyz",), "text frames", read_xyz, files=(".xyz",), one_file=True)
    monkeypatch.setattr(io, "FORMATS", (*io.FORMATS, row))
    path = tmp_path / "walk.xyz"
    np.savetxt(path, np.random.default_rng(0).uniform(0, 10, (4 * 20, 2)))
    assert io.detect_format(path) == "xyz"
    seq = io.load_sequence(path, frames="1:3", scale=2.0)
    assert calls == [("walk.xyz", "1:3", 2.0)] and len(seq) == 4
    with pytest.raises(ConfigError, match="do not apply to the xyz format"):
        io.load_sequence(path, stride=2)
    # the service derives its uploads from the same table (at import: the bundled rows here)
    assert {fmt for _, fmt in UPLOAD_FORMATS} == {f.name for f in FORMATS if f.one_file}


# ---- one read budget (issue 17 item 2) --------------------------------------------------------


def _flaser_log(scans: int, beams: int = 10) -> bytes:
    ranges = " ".join(f"{2 + 0.1 * b:.1f}" for b in range(beams))
    return "".join(f"FLASER {beams} {ranges} {0.1 * i} 0 0 {0.1 * i} 0 0 {i} h {i}\n" for i in range(scans)).encode()


def _tar(entries: dict[str, bytes]) -> bytes:
    import io
    import tarfile

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@pytest.mark.parametrize("compress", ["gzip", "bz2", "lzma"])
def test_a_compressed_tar_named_tar_is_read_and_budgeted(tmp_path: Path, compress: str) -> None:
    import importlib

    module = importlib.import_module(compress)
    frames = {f"{i:03d}.pcd": format_pcd(np.random.default_rng(i).uniform(0, 1, (30, 2))) for i in range(3)}
    path = tmp_path / "frames.tar"
    path.write_bytes(module.compress(_tar(frames)))
    assert len(load_sequence(path)) == 3
    path.write_bytes(module.compress(_tar({**frames, "junk.bin": bytes(4_000_000)})))
    with pytest.raises(FormatError, match="inflates to more than the limit of 1000000 bytes"):
        load_sequence(path, max_extract_bytes=1_000_000)


def test_a_carmen_log_is_streamed_line_by_line(tmp_path: Path) -> None:
    path = tmp_path / "robot.log.gz"
    path.write_bytes(gzip.compress(_flaser_log(4) + b"#" * (2 << 20)))
    with pytest.raises(FormatError, match=r"robot\.log\.gz:5: a line longer than 1048576 characters"):
        load_sequence(path)
    path.write_bytes(gzip.compress(_flaser_log(40)))
    assert len(load_sequence(path)) == 40
    with pytest.raises(FormatError, match="holds more than the limit of 300 points"):
        load_sequence(path, max_points=300)


def test_one_budget_spans_a_zip_and_the_npz_inside(tmp_path: Path) -> None:
    seq = Sequence(frames=[np.random.default_rng(i).normal(size=(50, 3)) for i in range(3)], poses=None)
    write_npz(seq, tmp_path / "seq.npz")
    npz = (tmp_path / "seq.npz").read_bytes()
    archive = tmp_path / "wrapped.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("seq.npz", npz)
    assert len(load_sequence(archive)) == 3
    # the zip alone fits, the zip and the arrays together do not
    with pytest.raises(FormatError, match="the limit of"):
        load_sequence(archive, max_extract_bytes=len(npz) + 200)
    with pytest.raises(FormatError, match=r"points\.npy: holds more than the limit of 149 points"):
        load_sequence(archive, max_points=149)
    assert not list(tmp_path.glob("strep-zip-*"))


def test_point_cloud_headers_are_checked_before_open3d_reads(tmp_path: Path) -> None:
    from strep_core.io.limits import declared_cloud_points

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(2):
        write_ply(folder / f"f{i}.ply", np.random.default_rng(i).normal(size=(40, 3)))
    assert declared_cloud_points((folder / "f0.ply").read_bytes()[:4096]) == 40
    assert declared_cloud_points(format_pcd(np.zeros((7, 3)))) == 7
    assert declared_cloud_points(b"POINTS " + b"9" * 5000 + b"\nDATA ascii\n") == 10**18
    assert len(load_sequence(folder)) == 2
    with pytest.raises(FormatError, match=r"f1\.ply: declares more than the limit of 60 points"):
        load_sequence(folder, max_points=60)
