"""What a LiDAR's scans say about the sensor: its field of view, its ranges, its vertical axis.

The probe (`strep_core.profiles.probe`) recognises a LiDAR from these measures, and the
``lidar`` profile turns its yaw search about the vertical axis estimated here
(docs/design/lidar.md):

* `sensor_geometry`: on a few frames, the spread of the ray directions (the smallest-eigenvalue
  direction of their scatter is the axis a spinning or wide solid-state LiDAR sweeps about), the
  azimuth extent about that axis (360 degrees for lidar_balm, about 60 for a depth camera) and
  range percentiles (15.5 m at the 95th on lidar_balm, under 5 m for 7-Scenes);
* `vertical_axis`: that sweep axis, refined by the normals of the horizontal surfaces (floor,
  ceiling, ground) within `REFINE_CONE_DEG` of it: a hand-held LiDAR tilts by up to 36 degrees
  on lidar_balm, and the refined axis follows the floor where the sweep axis follows the sensor.

numpy and scipy only (normals by PCA of each point's neighbours); lengths in the sequence's unit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from strep_core.sequence import Sequence
from strep_core.voxels import first_per_cell

REFINE_CONE_DEG = 25.0  # normals within this angle of the sweep axis belong to horizontal surfaces
GEOMETRY_FRAMES = 4  # frames measured, spread evenly over the sequence
GEOMETRY_POINTS = 20_000  # points per frame measured at most (an even stride)


def _frames(seq: Sequence, n: int = GEOMETRY_FRAMES) -> list[np.ndarray]:
    """Up to ``n`` evenly spaced frames, centred on their sensor and strided to `GEOMETRY_POINTS`."""
    assert seq.origins is not None
    idx = sorted({int(i) for i in np.linspace(0, len(seq) - 1, min(n, len(seq))).round()})
    out = []
    for i in idx:
        f = seq.frames[i] - seq.origins[i]
        out.append(f[:: max(1, len(f) // GEOMETRY_POINTS)])
    return out


def sweep_axis(points: np.ndarray) -> np.ndarray:
    """``(3,)`` unit direction of least spread of the rays to ``points`` ``(N, 3)`` (sensor at 0):
    the axis a LiDAR sweeps its beams about (up to sign); sign chosen with a positive z."""
    r = np.linalg.norm(points, axis=1)
    u = points[r > 0] / r[r > 0, None]
    _, vecs = np.linalg.eigh(u.T @ u / max(len(u), 1))
    axis = vecs[:, 0]
    return axis if axis[2] >= 0 else -axis


def azimuth_extent(points: np.ndarray, axis: np.ndarray) -> float:
    """Degrees of azimuth about ``axis`` that the rays to ``points`` cover: 360 less the widest
    empty sector (points within 1 degree of the axis ignored)."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    x, y = points @ e1, points @ e2
    keep = np.hypot(x, y) > np.linalg.norm(points, axis=1) * np.sin(np.radians(1.0))
    az = np.sort(np.degrees(np.arctan2(y[keep], x[keep])))
    if len(az) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([az, [az[0] + 360.0]]))
    return float(360.0 - gaps.max())


def pca_normals(points: np.ndarray, radius: float, *, neighbours: int = 16) -> np.ndarray:
    """``(N, 3)`` unit normals of ``points`` from a PCA of up to ``neighbours`` nearest neighbours
    within ``radius``; rows of zeros where fewer than 5 neighbours lie within it."""
    from scipy.spatial import cKDTree

    k = min(neighbours, len(points))
    d, idx = cKDTree(points).query(points, k=k, distance_upper_bound=radius)
    ok = np.isfinite(d)
    nb = points[np.where(ok, idx, 0)]
    w = ok[..., None].astype(np.float64)
    count = np.maximum(w.sum(axis=1), 1.0)
    centred = (nb - ((nb * w).sum(axis=1) / count)[:, None]) * w
    cov = np.einsum("nki,nkj->nij", centred, centred)
    _, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]
    normals[ok.sum(axis=1) < 5] = 0.0
    return normals


def refine_axis(normals: np.ndarray, axis: np.ndarray, cone_deg: float = REFINE_CONE_DEG) -> np.ndarray:
    """``axis`` moved to the mean direction of the ``normals`` ``(N, 3)`` within ``cone_deg`` of it
    (signs aligned; three rounds): the vertical of the horizontal surfaces near the guess. The
    guess is returned when fewer than 2 % of the normals lie within the cone."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    normals = np.asarray(normals, dtype=np.float64)
    cos = np.cos(np.radians(cone_deg))
    for _ in range(3):
        dots = normals @ axis
        near = np.abs(dots) > cos
        if near.sum() < max(10, 0.02 * len(normals)):
            break
        mean = (normals[near] * np.sign(dots[near])[:, None]).sum(axis=0)
        axis = mean / np.linalg.norm(mean)
    return axis


def sensor_geometry(seq: Sequence) -> dict[str, Any]:
    """What a few frames of a 3D ``seq`` say about the sensor (degrees; the sequence's unit).

    Returns ``azimuth_deg`` (median over frames of `azimuth_extent` about the sweep axis),
    ``range_p50`` and ``range_p95`` (percentiles of the point ranges) and ``sweep_axis`` (the
    frames' median `sweep_axis`, a unit 3-list).
    """
    frames = _frames(seq)
    axes = np.stack([sweep_axis(f) for f in frames])
    axis = np.median(axes, axis=0)
    axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0 else np.array([0.0, 0.0, 1.0])
    ranges = np.concatenate([np.linalg.norm(f, axis=1) for f in frames])
    return {
        "azimuth_deg": float(np.median([azimuth_extent(f, a) for f, a in zip(frames, axes, strict=True)])),
        "range_p50": float(np.percentile(ranges, 50)),
        "range_p95": float(np.percentile(ranges, 95)),
        "sweep_axis": [float(c) for c in axis],
    }


def vertical_axis(seq: Sequence, *, voxel: float | None = None) -> np.ndarray:
    """``(3,)`` unit vertical axis of a LiDAR sequence in its sensors' frame: the sweep axis of a
    few frames, refined by their horizontal surfaces' normals (`refine_axis`), normals by PCA
    within ``4 voxel`` (default voxel: 0.04 of the scale)."""
    frames = _frames(seq)
    guess = np.median(np.stack([sweep_axis(f) for f in frames]), axis=0)
    guess = guess / np.linalg.norm(guess) if np.linalg.norm(guess) > 0 else np.array([0.0, 0.0, 1.0])
    cell = voxel if voxel is not None else 0.04 * seq.scale()
    normals = []
    for f in frames:
        normals.append(pca_normals(f[first_per_cell(f, cell)], 4 * cell))
    axis = refine_axis(np.concatenate(normals), guess)
    return axis if axis @ guess >= 0 else -axis


def kiss_voxel(seq: Sequence) -> float:
    """KISS-ICP's own voxel for a LiDAR, its maximum range / 100 (1 m for its default 100 m), with
    the data's maximum range taken as the 99.9th percentile of the point ranges (a few stray
    returns lie at 187 m in lidar_balm, 99.9 % within 27 m): 0.27 m here, where the project's rule
    from the point spacing gives 0.05 m (KISS 0.255 m ATE in 319 s; 0.0095 m in 40 s at 0.27 m,
    0.021 m at KISS's plain 1 m)."""
    assert seq.origins is not None
    step = max(1, len(seq) // 32)
    ranges = np.concatenate(
        [np.linalg.norm(f - o, axis=1) for f, o in zip(seq.frames[::step], seq.origins[::step], strict=True)]
    )
    return float(np.percentile(ranges, 99.9)) / 100
