"""Open3D clouds for registration: building and preparing them, and the planar projections.

2D frames are registered in 3D as ``z = 0`` points with in-plane normals (`normals_2d`); every
3D estimate is projected back onto SE(2) (`project_planar`, `from_se3`), so 2D results are
exactly SE(2). Open3D is imported inside functions (it is heavy).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from strep_core import geometry as g
from strep_core.errors import RegistrationError
from strep_core.registration.params import RegistrationParams

if TYPE_CHECKING:  # pragma: no cover
    from strep_core._open3d import o3d


@contextlib.contextmanager
def open3d_quiet(threads: int | None = None) -> Iterator[Any]:
    """Import Open3D, silence its log and bound its threads (then restore them); yields the module."""
    from strep_core._open3d import o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        if threads is None:
            yield o3d
            return
        previous = o3d.utility.get_max_threads()
        o3d.utility.set_max_threads(int(threads))
        try:
            yield o3d
        finally:
            o3d.utility.set_max_threads(previous)


def project_planar(transform: np.ndarray) -> np.ndarray:
    """Nearest planar motion of 3D transforms ``(..., 4, 4)``: keep yaw and x, y; z = 0.

    Returns ``(..., 4, 4)`` SE(2) poses embedded in SE(3) (rotation about z only).
    """
    transform = np.asarray(transform, dtype=np.float64)
    yaw = np.arctan2(transform[..., 1, 0] - transform[..., 0, 1], transform[..., 0, 0] + transform[..., 1, 1])
    out = np.zeros_like(transform)
    c, s = np.cos(yaw), np.sin(yaw)
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 0, 3], out[..., 1, 3] = transform[..., 0, 3], transform[..., 1, 3]
    out[..., 2, 2] = out[..., 3, 3] = 1.0
    return out


def from_se3(transform: np.ndarray, dim: int) -> np.ndarray:
    """``(..., 4, 4)`` -> poses of dimension ``dim``: ``(..., 3, 3)`` SE(2) (projected) or as is."""
    if dim == 3:
        return np.asarray(transform, dtype=np.float64)
    planar = project_planar(transform)
    out = np.zeros((*planar.shape[:-2], 3, 3))
    out[..., :2, :2] = planar[..., :2, :2]
    out[..., :2, 2] = planar[..., :2, 3]
    out[..., 2, 2] = 1.0
    return out


def normals_2d(points: np.ndarray, *, neighbours: int = 6, origin: np.ndarray | None = None) -> np.ndarray:
    """Unit normals of 2D points from a PCA of each point's nearest neighbours.

    The normal is the eigenvector of the smallest eigenvalue of the neighbourhood covariance.

    Args:
        points: ``(N, 2)`` points.
        neighbours: neighbourhood size, the point itself included (at least 2; capped at N).
        origin: ``(2,)`` sensor position; normals are flipped to face it (``None``: the origin).

    Returns:
        ``(N, 2)`` unit normals.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise RegistrationError(f"normals_2d needs (N, 2) points, got {points.shape}")
    k = min(max(int(neighbours), 2), len(points))
    if k < 2:
        raise RegistrationError("normals_2d needs at least 2 points")
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx]  # (N, k, 2)
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred)
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    normals = vecs[:, :, 0]
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    view = (np.zeros(2) if origin is None else np.asarray(origin, dtype=np.float64)) - points
    flip = np.einsum("ni,ni->n", normals, view) < 0
    normals[flip] *= -1.0
    return normals


def make_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """An Open3D point cloud from ``(N, 2|3)`` points (2D embedded at ``z = 0``) and normals."""
    from strep_core._open3d import o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(g.pad_points(np.asarray(points, np.float64))))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(g.pad_points(np.asarray(normals, np.float64)))
    return cloud


def prepare_frame(
    points: np.ndarray, params: RegistrationParams, *, origin: np.ndarray | None = None
) -> o3d.geometry.PointCloud:
    """Downsample one frame and give it normals, ready for point-to-plane ICP.

    Args:
        points: ``(N, D)`` points in the frame's local coordinates.
        params: resolved settings (voxel, normal neighbourhood).
        origin: ``(D,)`` sensor position in the same coordinates; normals face it.

    Returns:
        An Open3D cloud in 3D (``z = 0`` for 2D frames) with unit normals.
    """
    from strep_core._open3d import o3d

    points = np.asarray(points, dtype=np.float64)
    dim = points.shape[1]
    origin = np.zeros(dim) if origin is None else np.asarray(origin, dtype=np.float64)
    cloud = make_cloud(points)
    if params.voxel is not None:
        cloud = cloud.voxel_down_sample(params.voxel)
    if len(cloud.points) < 3:
        raise RegistrationError(f"a frame keeps {len(cloud.points)} points after downsampling; need 3")
    if dim == 2:
        pts2 = np.asarray(cloud.points)[:, :2]
        cloud.normals = o3d.utility.Vector3dVector(
            g.pad_points(normals_2d(pts2, neighbours=params.normal_neighbours, origin=origin))
        )
    else:
        cloud.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=params.normal_radius, max_nn=params.normal_max_nn)
        )
        cloud.orient_normals_towards_camera_location(origin)
    return cloud


def transform_cloud(cloud: o3d.geometry.PointCloud, transform: np.ndarray) -> o3d.geometry.PointCloud:
    """A transformed copy of a cloud (points and normals) by a ``(4, 4)`` transform."""
    from strep_core._open3d import o3d

    out = o3d.geometry.PointCloud(cloud)
    out.transform(np.asarray(transform, dtype=np.float64))
    return out


def information_matrix(
    source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, transform: np.ndarray, distance: float
) -> np.ndarray:
    """``(6, 6)`` information matrix of a source -> target ``(4, 4)`` alignment (Open3D's)."""
    from strep_core._open3d import o3d

    return np.asarray(
        o3d.pipelines.registration.get_information_matrix_from_point_clouds(source, target, distance, transform)
    )
