"""Losses of the learned methods: Chamfer (KD-tree + gather), free-space samples, occupancy BCE."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from strep_core import geometry as g
from strep_core import losses
from strep_core.model import OccupancyMLP
from strep_core.pairs import frame_pairs, pair_queries


@pytest.fixture(autouse=True)
def _one_thread():
    """Tiny networks: one thread avoids the cost of waking a pool on a shared CPU."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _grid(n: int = 10, spacing: float = 1.0) -> np.ndarray:
    x, y = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    return np.c_[x.ravel(), y.ravel()]


def test_chamfer_of_a_set_with_itself_is_zero() -> None:
    a = torch.tensor(np.random.default_rng(0).normal(size=(200, 3)))
    assert losses.chamfer(a, a.clone()).item() == 0.0


def test_chamfer_of_a_shifted_grid_is_known() -> None:
    # On a unit grid shifted by (0.1, 0.05) every point's nearest neighbour is its own copy,
    # so both directions give N * |offset|^2.
    a = torch.tensor(_grid())
    offset = torch.tensor([0.1, 0.05], dtype=torch.float64)
    value = losses.chamfer(a, a + offset).item()
    assert value == pytest.approx(2 * len(a) * (0.1**2 + 0.05**2), rel=1e-12)
    # truncated: every match costs min(d^2, t^2)
    t = 0.05
    assert losses.chamfer(a, a + offset, robust="truncated", threshold=t).item() == pytest.approx(2 * len(a) * t * t)


def _brute_force(points: np.ndarray, frame: np.ndarray, pairs: np.ndarray, query: np.ndarray) -> float:
    total, count = 0.0, 0
    for i, j in pairs:
        q = points[query[frame[query] == i]]
        tgt = points[frame == j]
        d2 = ((q[:, None, :] - tgt[None, :, :]) ** 2).sum(-1).min(1)
        total += d2.sum()
        count += len(q)
    return total / count


def test_kdtree_chamfer_equals_brute_force() -> None:
    rng = np.random.default_rng(1)
    sizes = [40, 55, 33, 60, 47, 52]  # frames of different sizes, as in 3D
    frame = np.repeat(np.arange(len(sizes)), sizes)
    points = rng.normal(size=(len(frame), 3)) * 5.0 + frame[:, None] * 0.7
    pairs = frame_pairs(len(sizes), 2)
    query = np.sort(rng.choice(len(frame), 150, replace=False))
    value = losses.neighbourhood_chamfer(torch.tensor(points), frame, pairs, query=query).item()
    assert value == pytest.approx(_brute_force(points, frame, pairs, query), abs=1e-6)


def test_frame_pairs_temporal_and_spatial() -> None:
    pairs = frame_pairs(6, 2)
    assert len(pairs) == 2 * (5 + 4)  # both orders of |i-j| = 1 and 2
    assert set(map(tuple, pairs)) == {(i, j) for i in range(6) for j in range(6) if 0 < abs(i - j) <= 2}
    # frames 0 and 9 are at the same place: a spatial pair beyond the window
    pos = np.c_[np.arange(10.0), np.zeros(10)]
    pos[9] = pos[0] + 0.1
    spatial = {tuple(p) for p in frame_pairs(10, 2, positions=pos, radius=0.5)}
    assert (0, 9) in spatial and (9, 0) in spatial
    assert (0, 5) not in spatial


def test_pair_queries_cover_each_pair_once() -> None:
    frame = np.repeat(np.arange(3), [4, 2, 3])
    src, target = pair_queries(frame, np.array([[0, 1], [2, 0]]))
    assert src.tolist() == [0, 1, 2, 3, 6, 7, 8]
    assert target.tolist() == [1, 1, 1, 1, 0, 0, 0]


def test_chamfer_gradient_reaches_poses() -> None:
    pts = torch.tensor(_grid(8), dtype=torch.float64)
    xi = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.1, 0.01]], dtype=torch.float64, requires_grad=True)
    poses = g.se2_from_xytheta(xi)
    world = torch.cat([g.apply(poses[0], pts), g.apply(poses[1], pts)])
    frame = np.repeat([0, 1], len(pts))
    loss = losses.neighbourhood_chamfer(world, frame, frame_pairs(2, 1))
    loss.backward()
    assert xi.grad is not None and torch.isfinite(xi.grad).all()
    # the gradient of the moved frame points back towards alignment
    assert xi.grad[1, 0] > 0 and xi.grad[1, 1] < 0
    assert torch.allclose(xi.grad[0, :2], -xi.grad[1, :2], atol=1e-9)


def test_weighted_matches_are_a_weighted_mean() -> None:
    """Weights scale each match's robust cost: two matches 1 and 2 apart, weights 1 and 0.25."""
    pts = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 5.0], [2.0, 5.0]])
    src, idx = np.array([0, 2]), np.array([1, 3])
    plain = losses.chamfer_matches(pts, src, idx)
    weighted = losses.chamfer_matches(pts, src, idx, weights=np.array([1.0, 0.25]))
    assert float(plain) == pytest.approx((1.0 + 4.0) / 2)
    assert float(weighted) == pytest.approx((1.0 + 0.25 * 4.0) / 2)


def test_robust_forms() -> None:
    d2 = torch.tensor([0.0, 0.25, 4.0])
    assert losses.robust_squared(d2, robust="none", threshold=1.0).tolist() == [0.0, 0.25, 4.0]
    assert losses.robust_squared(d2, robust="truncated", threshold=1.0).tolist() == [0.0, 0.25, 1.0]
    assert losses.robust_squared(d2, robust="huber", threshold=1.0).tolist() == pytest.approx([0.0, 0.25, 3.0])


def test_free_space_samples_lie_on_the_rays() -> None:
    rng = np.random.default_rng(2)
    origins = torch.tensor(rng.normal(size=(50, 2)))
    hits = origins + torch.tensor(rng.normal(size=(50, 2)) * 3.0)
    gen = torch.Generator().manual_seed(0)
    s = losses.free_space_samples(origins, hits, gen, per_ray=4)
    assert s.shape == (200, 2)
    o = origins.repeat_interleave(4, 0)
    ray = hits.repeat_interleave(4, 0) - o
    rel = s - o
    cross = rel[:, 0] * ray[:, 1] - rel[:, 1] * ray[:, 0]
    t = (rel * ray).sum(-1) / (ray * ray).sum(-1)
    assert cross.abs().max() < 1e-9
    assert (t >= 0).all() and (t <= 1).all()
    assert t.std() > 0.2  # spread along the segment, not bunched


def test_occupancy_bce_falls_when_the_mlp_learns_a_fixed_map() -> None:
    torch.manual_seed(0)
    angles = torch.linspace(0, 2 * np.pi, 256)
    hits = torch.stack([torch.cos(angles), torch.sin(angles)], 1)  # a circular room, sensor inside
    origins = torch.zeros_like(hits)
    mlp = OccupancyMLP(2, [32, 64, 32])
    opt = torch.optim.Adam(mlp.parameters(), lr=3e-3)
    gen = torch.Generator().manual_seed(0)
    values = []
    for _ in range(150):
        free = losses.free_space_samples(origins, hits, gen, per_ray=1)
        loss = losses.occupancy_bce(mlp(hits), mlp(free))
        opt.zero_grad()
        loss.backward()
        opt.step()
        values.append(loss.item())
    assert values[0] > 1.2  # about 2 ln 2 for an untrained network
    assert np.mean(values[-10:]) < 0.6 * values[0]


def test_weak_directions_penalise_a_corridor_axis_only() -> None:
    """Two walls along x (normals all along y): moving along x costs fully, across nothing; a
    square room is constrained both ways; a frame without normals is free both ways."""
    corridor = np.tile([0.0, 1.0], (50, 1))
    np.testing.assert_allclose(losses.weak_directions(corridor), np.diag([1.0, 0.0]), atol=1e-12)
    room = np.r_[np.tile([1.0, 0.0], (25, 1)), np.tile([0.0, -1.0], (25, 1))]
    np.testing.assert_allclose(losses.weak_directions(room), np.zeros((2, 2)), atol=1e-12)
    np.testing.assert_allclose(losses.weak_directions(np.zeros((3, 2))), np.eye(2))
