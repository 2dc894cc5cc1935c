"""Rigid-body geometry in 2D and 3D, for numpy arrays and torch tensors alike.

Poses are homogeneous matrices throughout the library:

* SE(2): ``(..., 3, 3)``, SE(3): ``(..., 4, 4)``; a pose maps points of a frame's local
  (sensor) coordinates into the world: ``p_world = R @ p_local + t``.
* Tangent vectors: se(2) ``(..., 3)`` as ``(v_x, v_y, theta)``, se(3) ``(..., 6)`` as
  ``(rho_x, rho_y, rho_z, omega_x, omega_y, omega_z)`` (translation first).
* Pose vectors (what networks regress): 2D ``(x, y, theta)``, 3D ``(t_x, t_y, t_z, omega)``
  with ``omega`` an axis-angle rotation. Unlike the tangent vector, the translation part of a
  pose vector *is* the translation of the pose.

Every function accepts numpy arrays or torch tensors (any float dtype, any leading batch
shape) and returns the same kind. Angles are in radians; lengths are in the sequence's unit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

Array = Any  # np.ndarray | torch.Tensor

_SMALL = 1e-4  # below this angle, Taylor series replace the closed forms


# --------------------------------------------------------------------------------------------
# numpy / torch shims


def _is_torch(x: Array) -> bool:
    return type(x).__module__.startswith("torch")


def _xp(x: Array) -> Any:
    if _is_torch(x):
        import torch

        return torch
    return np


def _stack(xs: list[Array], axis: int) -> Array:
    if _is_torch(xs[0]):
        import torch

        return torch.stack(xs, dim=axis)
    return np.stack(xs, axis=axis)


def _norm(x: Array, axis: int = -1) -> Array:
    if _is_torch(x):
        import torch

        return torch.linalg.norm(x, dim=axis)
    return np.linalg.norm(x, axis=axis)


def _swap(x: Array) -> Array:
    """Transpose the last two axes."""
    return x.transpose(-1, -2) if _is_torch(x) else np.swapaxes(x, -1, -2)


def _eye(n: int, like: Array) -> Array:
    if _is_torch(like):
        import torch

        return torch.eye(n, dtype=like.dtype, device=like.device).expand(*like.shape[:-1], n, n)
    return np.broadcast_to(np.eye(n, dtype=like.dtype), (*like.shape[:-1], n, n))


def _asfloat(x: Array) -> Array:
    if _is_torch(x):
        return x if x.is_floating_point() else x.double()
    x = np.asarray(x)
    return x if np.issubdtype(x.dtype, np.floating) else x.astype(np.float64)


def _where(c: Array, a: Array, b: Array) -> Array:
    return _xp(c).where(c, a, b)


def _clip(x: Array, lo: float, hi: float) -> Array:
    return x.clamp(lo, hi) if _is_torch(x) else np.clip(x, lo, hi)


def homogeneous(rot: Array, trans: Array) -> Array:
    """Build ``(..., D+1, D+1)`` from ``rot (..., D, D)`` and ``trans (..., D)``."""
    xp = _xp(rot)
    d = rot.shape[-1]
    top = xp.concatenate([rot, trans[..., :, None]], -1)
    bottom = xp.zeros_like(top[..., :1, :])
    bottom[..., 0, d] = 1.0
    return xp.concatenate([top, bottom], -2)


# --------------------------------------------------------------------------------------------
# Dimension-generic operations on homogeneous matrices


def dim_of(pose: Array) -> int:
    """Spatial dimension D (2 or 3) of a pose ``(..., D+1, D+1)``."""
    return int(pose.shape[-1]) - 1


def identity(dim: int, n: int | None = None, *, dtype: Any = np.float64) -> np.ndarray:
    """Identity pose(s): ``(D+1, D+1)``, or ``(n, D+1, D+1)`` when ``n`` is given."""
    eye = np.eye(dim + 1, dtype=dtype)
    return eye if n is None else np.repeat(eye[None], n, axis=0)


def rotation(pose: Array) -> Array:
    """Rotation block ``(..., D, D)`` of a pose ``(..., D+1, D+1)``."""
    d = dim_of(pose)
    return pose[..., :d, :d]


def translation(pose: Array) -> Array:
    """Translation ``(..., D)`` of a pose ``(..., D+1, D+1)``."""
    d = dim_of(pose)
    return pose[..., :d, d]


def inverse(pose: Array) -> Array:
    """Inverse of a rigid pose ``(..., D+1, D+1)`` (uses ``R^T``, not a general inverse)."""
    rot_t = _swap(rotation(pose))
    t = translation(pose)
    return homogeneous(rot_t, -(rot_t @ t[..., :, None])[..., 0])


def apply(pose: Array, points: Array) -> Array:
    """Transform points ``(..., N, D)`` by poses ``(..., D+1, D+1)``: ``R p + t``."""
    return points @ _swap(rotation(pose)) + translation(pose)[..., None, :]


def relative(a: Array, b: Array) -> Array:
    """Pose of ``b`` seen from ``a``: ``a^-1 b``."""
    return inverse(a) @ b


# --------------------------------------------------------------------------------------------
# SO(2) / SE(2)


def so2(theta: Array) -> Array:
    """Rotation matrices ``(..., 2, 2)`` for angles ``(...)`` in radians."""
    theta = _asfloat(theta)
    xp = _xp(theta)
    c, s = xp.cos(theta), xp.sin(theta)
    return _stack([_stack([c, -s], -1), _stack([s, c], -1)], -2)


def so2_angle(rot: Array) -> Array:
    """Angle in ``(-pi, pi]`` of rotations ``(..., 2, 2)``."""
    xp = _xp(rot)
    return xp.arctan2(rot[..., 1, 0], rot[..., 0, 0])


def se2_from_xytheta(v: Array) -> Array:
    """Pose ``(..., 3, 3)`` from pose vectors ``(..., 3)`` = ``(x, y, theta)``."""
    v = _asfloat(v)
    return homogeneous(so2(v[..., 2]), v[..., :2])


def se2_to_xytheta(pose: Array) -> Array:
    """Pose vectors ``(..., 3)`` = ``(x, y, theta)`` of poses ``(..., 3, 3)``."""
    return _xp(pose).concatenate([translation(pose), so2_angle(rotation(pose))[..., None]], -1)


def _se2_v(theta: Array) -> tuple[Array, Array]:
    """Coefficients ``a = sin(t)/t`` and ``b = (1 - cos(t))/t`` with Taylor series near 0."""
    xp = _xp(theta)
    small = xp.abs(theta) < _SMALL
    safe = _where(small, xp.ones_like(theta), theta)
    t2 = theta * theta
    a = _where(small, 1.0 - t2 / 6.0, xp.sin(safe) / safe)
    b = _where(small, theta / 2.0 - theta * t2 / 24.0, (1.0 - xp.cos(safe)) / safe)
    return a, b


def se2_exp(xi: Array) -> Array:
    """Exponential map se(2) ``(..., 3)`` -> SE(2) ``(..., 3, 3)``."""
    xi = _asfloat(xi)
    theta = xi[..., 2]
    a, b = _se2_v(theta)
    vx, vy = xi[..., 0], xi[..., 1]
    t = _stack([a * vx - b * vy, b * vx + a * vy], -1)
    return homogeneous(so2(theta), t)


def se2_log(pose: Array) -> Array:
    """Logarithm SE(2) ``(..., 3, 3)`` -> se(2) ``(..., 3)``, angle in ``(-pi, pi]``."""
    theta = so2_angle(rotation(pose))
    a, b = _se2_v(theta)
    det = a * a + b * b
    tx, ty = pose[..., 0, 2], pose[..., 1, 2]
    # inverse of [[a, -b], [b, a]] is [[a, b], [-b, a]] / det
    vx = (a * tx + b * ty) / det
    vy = (-b * tx + a * ty) / det
    return _stack([vx, vy, theta], -1)


# --------------------------------------------------------------------------------------------
# SO(3) / SE(3)


def hat3(w: Array) -> Array:
    """Skew-symmetric matrices ``(..., 3, 3)`` of vectors ``(..., 3)``: ``hat(w) v = w x v``."""
    z = w[..., 0] * 0
    return _stack(
        [
            _stack([z, -w[..., 2], w[..., 1]], -1),
            _stack([w[..., 2], z, -w[..., 0]], -1),
            _stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def _so3_coeffs(theta: Array) -> tuple[Array, Array, Array]:
    """``A = sin t / t``, ``B = (1 - cos t)/t^2``, ``C = (t - sin t)/t^3`` (Taylor near 0)."""
    xp = _xp(theta)
    small = theta < _SMALL
    safe = _where(small, xp.ones_like(theta), theta)
    t2 = theta * theta
    s, c = xp.sin(safe), xp.cos(safe)
    a = _where(small, 1.0 - t2 / 6.0, s / safe)
    b = _where(small, 0.5 - t2 / 24.0, (1.0 - c) / (safe * safe))
    cc = _where(small, 1.0 / 6.0 - t2 / 120.0, (safe - s) / (safe * safe * safe))
    return a, b, cc


def _theta3(w: Array) -> Array:
    """Norm of rotation vectors with a gradient that stays finite at zero."""
    xp = _xp(w)
    sq = (w * w).sum(-1)
    return xp.sqrt(_where(sq > 0, sq, xp.ones_like(sq))) * (sq > 0)


def so3_exp(w: Array) -> Array:
    """Rotation matrices ``(..., 3, 3)`` from axis-angle vectors ``(..., 3)`` (Rodrigues)."""
    w = _asfloat(w)
    theta = _theta3(w)
    a, b, _ = _so3_coeffs(theta)
    k = hat3(w)
    return _eye(3, w) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: Array) -> Array:
    """Axis-angle vectors ``(..., 3)`` of rotations ``(..., 3, 3)``; angle in ``[0, pi]``.

    Stable near 0 (Taylor series) and near pi (axis from the symmetric part).
    """
    xp = _xp(rot)
    tr = rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2]
    cos_t = _clip((tr - 1.0) / 2.0, -1.0, 1.0)
    theta = xp.arccos(cos_t)
    vee = _stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]],
        -1,
    )
    sin_t = xp.sin(theta)
    small = theta < _SMALL
    near_pi = theta > np.pi - 1e-2
    safe_sin = _where(small | near_pi, xp.ones_like(sin_t), sin_t)
    factor = _where(small, 0.5 + theta * theta / 12.0, theta / (2.0 * safe_sin))
    w = factor[..., None] * vee
    # Near pi: the symmetric part is cos(t) I + (1 - cos(t)) n n^T, exact for any angle;
    # take n from its best-conditioned column and the sign from the antisymmetric part.
    sym = (rot + _swap(rot)) / 2.0
    one_minus_cos = _clip(1.0 - cos_t, 1e-12, 2.0)
    nn = (sym - cos_t[..., None, None] * _eye(3, rot[..., 0])) / one_minus_cos[..., None, None]
    diag = _stack([nn[..., 0, 0], nn[..., 1, 1], nn[..., 2, 2]], -1)
    idx = diag.argmax(-1)
    if _is_torch(rot):
        col = xp.take_along_dim(nn, idx[..., None, None].expand(*nn.shape[:-1], 1), dim=-1)[..., 0]
    else:
        col = np.take_along_axis(nn, idx[..., None, None].repeat(3, -2), axis=-1)[..., 0]
    axis = col / _where(_norm(col) > 0, _norm(col), xp.ones_like(theta))[..., None]
    sign = xp.sign((axis * vee).sum(-1))
    sign = _where(sign == 0, xp.ones_like(sign), sign)
    w_pi = axis * (theta * sign)[..., None]
    return _where(near_pi[..., None], w_pi, w)


def se3_from_vector(v: Array) -> Array:
    """Pose ``(..., 4, 4)`` from pose vectors ``(..., 6)`` = ``(t, omega)``, omega axis-angle."""
    v = _asfloat(v)
    return homogeneous(so3_exp(v[..., 3:]), v[..., :3])


def se3_to_vector(pose: Array) -> Array:
    """Pose vectors ``(..., 6)`` = ``(t, omega)`` of poses ``(..., 4, 4)``."""
    return _xp(pose).concatenate([translation(pose), so3_log(rotation(pose))], -1)


def se3_exp(xi: Array) -> Array:
    """Exponential map se(3) ``(..., 6)`` = ``(rho, omega)`` -> SE(3) ``(..., 4, 4)``."""
    xi = _asfloat(xi)
    rho, w = xi[..., :3], xi[..., 3:]
    theta = _theta3(w)
    a, b, c = _so3_coeffs(theta)
    k = hat3(w)
    kk = k @ k
    eye = _eye(3, w)
    rot = eye + a[..., None, None] * k + b[..., None, None] * kk
    v = eye + b[..., None, None] * k + c[..., None, None] * kk
    return homogeneous(rot, (v @ rho[..., :, None])[..., 0])


def se3_log(pose: Array) -> Array:
    """Logarithm SE(3) ``(..., 4, 4)`` -> se(3) ``(..., 6)`` = ``(rho, omega)``."""
    xp = _xp(pose)
    w = so3_log(rotation(pose))
    theta = _theta3(w)
    a, b, _ = _so3_coeffs(theta)
    small = theta < _SMALL
    safe = _where(small, xp.ones_like(theta), theta)
    # V^-1 = I - K/2 + (1/t^2)(1 - A/(2B)) K^2
    d = _where(small, 1.0 / 12.0 + theta * theta / 720.0, (1.0 - a / (2.0 * b)) / (safe * safe))
    k = hat3(w)
    v_inv = _eye(3, w) - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (v_inv @ translation(pose)[..., :, None])[..., 0]
    return xp.concatenate([rho, w], -1)


# --------------------------------------------------------------------------------------------
# Dimension-dispatching helpers


def pose_from_vector(v: Array) -> Array:
    """Pose from a pose vector: ``(..., 3)`` -> SE(2), ``(..., 6)`` -> SE(3)."""
    n = v.shape[-1]
    if n == 3:
        return se2_from_xytheta(v)
    if n == 6:
        return se3_from_vector(v)
    raise ValueError(f"a pose vector has 3 (2D) or 6 (3D) entries, not {n}")


def pose_to_vector(pose: Array) -> Array:
    """Pose vector of a pose: SE(2) -> ``(x, y, theta)``, SE(3) -> ``(t, omega)``."""
    return se2_to_xytheta(pose) if dim_of(pose) == 2 else se3_to_vector(pose)


def exp(xi: Array) -> Array:
    """Exponential map for se(2) ``(..., 3)`` or se(3) ``(..., 6)``."""
    return se2_exp(xi) if xi.shape[-1] == 3 else se3_exp(xi)


def log(pose: Array) -> Array:
    """Logarithm for SE(2) ``(..., 3, 3)`` or SE(3) ``(..., 4, 4)``."""
    return se2_log(pose) if dim_of(pose) == 2 else se3_log(pose)


def rotation_angle(pose: Array) -> Array:
    """Rotation angle in radians ``(...)`` of poses, in ``[0, pi]``."""
    if dim_of(pose) == 2:
        return _xp(pose).abs(so2_angle(rotation(pose)))
    return _theta3(so3_log(rotation(pose)))


def to_se3(pose: np.ndarray) -> np.ndarray:
    """Embed SE(2) poses ``(..., 3, 3)`` in SE(3) ``(..., 4, 4)`` (z = 0, yaw only); SE(3) as is."""
    pose = np.asarray(pose, dtype=np.float64)
    if dim_of(pose) == 3:
        return pose
    out = np.zeros((*pose.shape[:-2], 4, 4))
    out[..., :2, :2] = pose[..., :2, :2]
    out[..., :2, 3] = pose[..., :2, 2]
    out[..., 2, 2] = 1.0
    out[..., 3, 3] = 1.0
    return out


def pad_points(points: np.ndarray) -> np.ndarray:
    """2D points ``(N, 2)`` -> ``(N, 3)`` with z = 0; 3D points unchanged."""
    points = np.asarray(points)
    if points.shape[-1] == 3:
        return points
    return np.concatenate([points, np.zeros((*points.shape[:-1], 1), points.dtype)], -1)


# --------------------------------------------------------------------------------------------
# Quaternions (x, y, z, w), for trajectory files


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from unit quaternions ``(..., 4)`` in ``(x, y, z, w)``."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` in ``(x, y, z, w)``, ``w >= 0``, of rotations ``(..., 3, 3)``."""
    rot = np.asarray(rot, dtype=np.float64)
    w = so3_log(rot)
    theta = np.linalg.norm(w, axis=-1)
    half = theta / 2.0
    scale = np.where(theta > 1e-12, np.sin(half) / np.where(theta > 1e-12, theta, 1.0), 0.5)
    q = np.concatenate([w * scale[..., None], np.cos(half)[..., None]], -1)
    return np.where(q[..., 3:4] < 0, -q, q)
