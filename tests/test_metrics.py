"""Metrics on hand-made cases with known answers, and on the real v1_pose0."""

from __future__ import annotations

import numpy as np
import pytest

from strep_core import geometry as g
from strep_core import metrics


def random_trajectory(dim: int, k: int = 30, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = 3 if dim == 2 else 6
    steps = g.exp(rng.normal(scale=0.3, size=(k, n)))
    out = [g.identity(dim)]
    for s in steps[1:]:
        out.append(out[-1] @ s)
    return np.stack(out)


@pytest.mark.parametrize("dim", [2, 3])
def test_rigidly_moved_copy_scores_zero(dim: int) -> None:
    gt = random_trajectory(dim)
    n = 3 if dim == 2 else 6
    motion = g.exp(np.linspace(0.5, 1.5, n))
    est = motion[None] @ gt
    frames = [np.random.default_rng(i).normal(size=(20, dim)) for i in range(len(gt))]
    assert metrics.ate(est, gt) < 1e-9
    assert metrics.point_l2(frames, est, gt) < 1e-9
    r = metrics.rpe(est, gt)
    assert r["rpe_trans"] < 1e-9 and r["rpe_rot_deg"] < 1e-6


def test_known_offset_gives_known_ate() -> None:
    """Poses on a circle of radius 10, estimates on radius 10 + d: no rigid motion helps, ATE = d."""
    k, d = 12, 0.25
    angles = np.arange(k) * 2 * np.pi / k
    gt = g.identity(2, k)
    gt[:, :2, 2] = 10.0 * np.stack([np.cos(angles), np.sin(angles)], 1)
    est = gt.copy()
    est[:, :2, 2] *= (10.0 + d) / 10.0
    assert metrics.ate(est, gt) == pytest.approx(d, abs=1e-12)
    # with no rotation error, every point is off by exactly its frame's position offset
    frames = [np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 3.0]])] * k
    assert metrics.point_l2(frames, est, gt) == pytest.approx(d, abs=1e-12)


def test_pairwise_errors_see_one_bad_frame() -> None:
    """One frame rotated by a in place: every pair with it is off by a, the others by 0."""
    k, a = 50, 0.1
    gt = g.identity(2, k)
    gt[:, 0, 2] = np.arange(k) * 10.0
    est = gt.copy()
    est[k // 2] = est[k // 2] @ g.se2_from_xytheta(np.array([0.0, 0.0, a]))
    assert metrics.ate(est, gt) == pytest.approx(0.0, abs=1e-9)
    errs = metrics.pairwise_errors(est, gt)
    assert errs["pair_rot_err_max_deg"] == pytest.approx(np.degrees(a), rel=1e-9)
    pairs = k * (k - 1) / 2
    assert errs["pair_rot_err_mean_deg"] == pytest.approx(np.degrees(a) * (k - 1) / pairs, rel=1e-9)


def test_point_l2_aligns_on_points_when_positions_do_not_fix_rotation() -> None:
    """A camera turning on the spot: positions are all equal, so only the points fix the alignment."""
    k = 8
    gt = g.se2_from_xytheta(np.stack([np.zeros(k), np.zeros(k), np.linspace(0, 2, k)], 1))
    motion = g.se2_from_xytheta(np.array([3.0, -1.0, 0.7]))
    est = motion[None] @ gt
    frames = [np.random.default_rng(i).normal(size=(30, 2)) + np.array([5.0, 0.0]) for i in range(k)]
    assert metrics.point_l2(frames, est, gt) < 1e-9


def test_align_rigid_recovers_motion_and_is_proper() -> None:
    rng = np.random.default_rng(5)
    src = rng.normal(size=(100, 3))
    rot = g.so3_exp(np.array([0.3, -1.2, 0.8]))
    t = np.array([1.0, -2.0, 0.5])
    r_est, t_est = metrics.align_rigid(src, src @ rot.T + t)
    np.testing.assert_allclose(r_est, rot, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    # a reflected target still yields a proper rotation
    r_ref, _ = metrics.align_rigid(src, src * np.array([1, 1, -1]))
    assert np.linalg.det(r_ref) == pytest.approx(1.0)


def test_v1_pose0_identity_matches_published_figure(v1_pose0) -> None:
    """DeepMapping reports 220.6 px for identity poses on this sequence."""
    assert metrics.ate(g.identity(2, len(v1_pose0)), v1_pose0.poses) == pytest.approx(220.6, abs=0.1)
