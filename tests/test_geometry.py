"""Group laws of SE(2)/SE(3) in numpy and torch, with hypothesis."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from strep_core import geometry as g

finite = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
angle = st.floats(-np.pi + 1e-3, np.pi - 1e-3)
tiny = st.floats(-1e-7, 1e-7)


def xi2() -> st.SearchStrategy[np.ndarray]:
    return st.tuples(finite, finite, angle).map(np.array)


def xi3(max_angle: float = np.pi - 1e-3) -> st.SearchStrategy[np.ndarray]:
    def make(v: tuple[float, ...]) -> np.ndarray:
        rho = np.array(v[:3])
        w = np.array(v[3:6])
        n = np.linalg.norm(w)
        if n > max_angle:
            w = w / n * max_angle
        return np.concatenate([rho, w])

    return st.tuples(*([finite] * 6)).map(make)


def is_rotation(r: np.ndarray, tol: float = 1e-9) -> bool:
    d = r.shape[-1]
    return bool(np.allclose(r @ np.swapaxes(r, -1, -2), np.eye(d), atol=tol)) and bool(
        np.allclose(np.linalg.det(r), 1.0, atol=tol)
    )


@settings(max_examples=60, deadline=None)
@given(st.one_of(xi2(), xi3()))
def test_exp_log_round_trip(xi: np.ndarray) -> None:
    pose = g.exp(xi)
    assert is_rotation(g.rotation(pose))
    np.testing.assert_allclose(g.log(pose), xi, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.one_of(xi2(), xi3()), st.one_of(xi2(), xi3()))
def test_inverse_and_identity(a: np.ndarray, b: np.ndarray) -> None:
    pa = g.exp(a)
    d = g.dim_of(pa)
    np.testing.assert_allclose(pa @ g.inverse(pa), np.eye(d + 1), atol=1e-9)  # poses compose by @
    np.testing.assert_allclose(g.identity(d) @ pa, pa, atol=1e-12)
    if len(a) == len(b):
        pb = g.exp(b)
        # (ab)^-1 = b^-1 a^-1
        np.testing.assert_allclose(g.inverse(pa @ pb), g.inverse(pb) @ g.inverse(pa), atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.one_of(xi2(), xi3()), arrays(np.float64, (7, 3), elements=finite))
def test_apply_matches_homogeneous_product(xi: np.ndarray, pts: np.ndarray) -> None:
    pose = g.exp(xi)
    d = g.dim_of(pose)
    p = pts[:, :d]
    homog = np.concatenate([p, np.ones((len(p), 1))], 1) @ pose.T
    np.testing.assert_allclose(g.apply(pose, p), homog[:, :d], atol=1e-9)
    # applying a pose then its inverse gives the points back
    np.testing.assert_allclose(g.apply(g.inverse(pose), g.apply(pose, p)), p, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.one_of(st.tuples(finite, finite, angle), st.tuples(*([finite] * 3), angle, angle, angle)))
def test_pose_vector_round_trip(v: tuple[float, ...]) -> None:
    vec = np.array(v)
    if len(vec) == 6 and np.linalg.norm(vec[3:]) >= np.pi:
        vec[3:] *= (np.pi - 1e-3) / np.linalg.norm(vec[3:])
    np.testing.assert_allclose(g.pose_to_vector(g.pose_from_vector(vec)), vec, atol=1e-8)


@settings(max_examples=40, deadline=None)
@given(st.tuples(tiny, tiny, tiny, tiny, tiny, tiny).map(np.array))
def test_near_identity(xi: np.ndarray) -> None:
    """Taylor branches: exp/log stay accurate for rotations of 1e-7 rad."""
    for v in (xi[:3], xi):
        pose = g.exp(v)
        np.testing.assert_allclose(g.log(pose), v, atol=1e-13)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float32_and_float64(dtype: type) -> None:
    rng = np.random.default_rng(3)
    for n in (3, 6):
        xi = rng.normal(size=(20, n)).astype(dtype)
        if n == 6:
            xi[:, 3:] *= 0.5
        pose = g.exp(xi)
        assert pose.dtype == dtype
        tol = 1e-4 if dtype == np.float32 else 1e-10
        np.testing.assert_allclose(g.log(pose), xi, atol=tol)
        eye = np.broadcast_to(np.eye(pose.shape[-1]), pose.shape)
        np.testing.assert_allclose(g.inverse(pose) @ pose, eye, atol=tol)


def test_rotation_by_pi() -> None:
    """so3_log is exact at and near a half turn, where the closed form divides by sin(pi)."""
    for axis in (np.array([1.0, 0, 0]), np.array([0, 0.6, 0.8]), np.array([-0.48, 0.6, 0.64])):
        for theta in (np.pi, np.pi - 1e-6, np.pi - 5e-4):
            w = axis / np.linalg.norm(axis) * theta
            got = g.so3_log(g.so3_exp(w))
            # w and -w are the same rotation at exactly pi
            assert np.allclose(got, w, atol=1e-6) or (theta == np.pi and np.allclose(got, -w, atol=1e-6))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_matches_numpy_and_has_gradients(dtype: torch.dtype) -> None:
    rng = np.random.default_rng(0)
    for n in (3, 6):
        xi = rng.normal(size=(8, n)) * 0.7
        xi[0] = 0.0  # gradient at exactly zero rotation must be finite
        t = torch.tensor(xi, dtype=dtype, requires_grad=True)
        pose_t = g.exp(t)
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        np.testing.assert_allclose(pose_t.detach().numpy(), g.exp(xi), atol=tol)
        pts = torch.tensor(rng.normal(size=(8, 5, n // 3 + 1 if n == 3 else 3)), dtype=dtype)
        g.apply(g.pose_from_vector(t), pts).square().sum().backward()
        assert t.grad is not None and torch.isfinite(t.grad).all()
        np.testing.assert_allclose(g.log(pose_t).detach().numpy(), xi, atol=10 * tol)


def test_quaternion_round_trip_and_yaw() -> None:
    rng = np.random.default_rng(1)
    rot = g.so3_exp(rng.normal(size=(50, 3)))
    q = g.rotation_to_quaternion(rot)
    assert (q[:, 3] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(g.quaternion_to_rotation(q), rot, atol=1e-12)
    # a 2D pose embeds as a yaw rotation about z
    yaw = 0.7
    q = g.rotation_to_quaternion(g.to_se3(g.se2_from_xytheta(np.array([1.0, 2.0, yaw])))[:3, :3])
    np.testing.assert_allclose(q, [0, 0, np.sin(yaw / 2), np.cos(yaw / 2)], atol=1e-12)
