"""A 2D lidar simulator on an occupancy image, as in DeepMapping and the STREP paper.

Conventions (the same as DeepMapping's data, see the shared data README):

* A map is a ``(size, size)`` bool image, ``True`` = occupied. Pixel ``occ[r, c]`` is the unit
  square centred on the point ``(x, y) = (c, r)``: ``x`` runs along columns, ``y`` along rows,
  both in map pixels.
* A pose is ``(x, y, theta)``: the sensor position in map pixels and its heading in radians;
  a point ``p`` of the sensor frame lies at ``R(theta) p + (x, y)`` in the map.
* A scan casts ``rays`` rays from the sensor, the first along the heading, then
  counter-clockwise every ``step_deg`` degrees (256 x 1.40625 = 360). A ray returns the point
  where it enters its first occupied pixel; rays that hit nothing (within ``max_range``) are
  dropped, so frames may have fewer points than rays.

Everything is seeded: the same seeds give bit-identical maps, trajectories and scans.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from strep_core import geometry as g
from strep_core.errors import ConfigError
from strep_core.io.pcd import format_pcd
from strep_core.sequence import Sequence
from strep_core.sim.floorplan import cached_map, free_distance

DEEPMAPPING_SCALE = 512.0  # DeepMapping stores local points in pixels / 512
DEFAULT_STEP_DEG = 1.40625  # 360 / 256

_JUMP_MIN = 3.0  # free-space distance (px) above which a ray leaps instead of stepping cells


# --------------------------------------------------------------------------------------------
# Trajectories


def _segment_clear(free: np.ndarray, a: np.ndarray, b: np.ndarray, clearance: float) -> np.ndarray:
    """For ``(M, 2)`` start and end points, whether every point of each segment keeps clearance."""
    h, w = free.shape
    n = int(np.ceil(np.max(np.linalg.norm(b - a, axis=1), initial=0.0))) + 2
    s = np.linspace(0.0, 1.0, n)
    pts = a[:, None, :] + s[None, :, None] * (b - a)[:, None, :]  # (M, n, 2)
    c = np.rint(pts).astype(np.int64)
    inside = (c[..., 0] >= 0) & (c[..., 0] < w) & (c[..., 1] >= 0) & (c[..., 1] < h)
    d = free[np.clip(c[..., 1], 0, h - 1), np.clip(c[..., 0], 0, w - 1)]
    return (inside & (d >= clearance)).all(axis=1)


def _free_ahead(free: np.ndarray, p: np.ndarray, heading: np.ndarray, horizon: float) -> np.ndarray:
    """Free distance (px, up to ``horizon``) from ``p (2,)`` along each heading ``(M,)``."""
    h, w = free.shape
    s = np.arange(0.0, horizon + 1.0, 2.0)
    pts = p[None, None, :] + s[None, :, None] * np.stack([np.cos(heading), np.sin(heading)], -1)[:, None]
    c = np.rint(pts).astype(np.int64)
    inside = (c[..., 0] >= 0) & (c[..., 0] < w) & (c[..., 1] >= 0) & (c[..., 1] < h)
    ok = inside & (free[np.clip(c[..., 1], 0, h - 1), np.clip(c[..., 0], 0, w - 1)] >= 2.0)
    blocked = ~ok
    return np.where(blocked.any(1), s[blocked.argmax(1)], horizon)


def make_trajectory(
    occ: np.ndarray,
    seed: int,
    *,
    frames: int = 256,
    max_turn_deg: float = 10.0,
    max_step: float = 16.0,
    clearance: float = 8.0,
    candidates: int = 12,
    free: np.ndarray | None = None,
) -> np.ndarray:
    """A seeded random walk in the free space of a map.

    Each step turns by an angle drawn uniformly in ``[-max_turn_deg, max_turn_deg]`` degrees,
    then moves ``U(0, max_step)`` pixels along the new heading. ``candidates`` such steps are
    drawn; those whose segment comes closer than ``clearance`` px to a wall are rejected, and
    one of the rest is picked among those with the most free space ahead (so the walk follows
    rooms and corridors instead of hugging walls). When every candidate is rejected the sensor
    turns in place by ``max_turn_deg``.

    Args:
        occ: ``(H, W)`` bool occupancy image.
        seed: the trajectory's seed.
        frames: number of poses K.
        max_turn_deg: largest heading change per step, degrees.
        max_step: largest translation per step, pixels.
        clearance: smallest distance from the sensor to a wall pixel centre, pixels.
        candidates: steps drawn per frame.
        free: optional precomputed `free_distance` of ``occ``.

    Returns:
        ``(K, 3)`` float64 poses ``(x, y, theta)``: pixels, radians in ``(-pi, pi]``.

    Raises:
        ConfigError: ``frames < 1`` or no free pixel with enough clearance to start from.
    """
    if frames < 1:
        raise ConfigError(f"a trajectory needs at least 1 frame, got {frames}")
    free = free_distance(occ) if free is None else free
    rng = np.random.default_rng([int(seed), 1])
    start_clear = max(3.0 * clearance, 24.0)
    ys, xs = np.nonzero(free >= start_clear)
    if len(xs) == 0:
        raise ConfigError(f"the map has no free pixel {start_clear:.0f} px away from walls")
    i = int(rng.integers(len(xs)))
    p = np.array([xs[i], ys[i]], dtype=np.float64) + rng.uniform(-0.5, 0.5, 2)
    theta = float(rng.uniform(-np.pi, np.pi))
    out = np.empty((frames, 3))
    out[0] = (p[0], p[1], theta)
    max_turn = np.radians(max_turn_deg)
    spin = 1.0
    for k in range(1, frames):
        dth = rng.uniform(-max_turn, max_turn, candidates)
        dist = rng.uniform(0.0, max_step, candidates)
        head = theta + dth
        ends = p[None] + dist[:, None] * np.stack([np.cos(head), np.sin(head)], -1)
        ok = _segment_clear(free, np.broadcast_to(p, ends.shape), ends, clearance)
        if ok.any():
            ahead = _free_ahead(free, p, head, 4.0 * max_step + 32.0)
            ahead = np.where(ok, ahead, -1.0)
            good = np.flatnonzero(ahead >= 0.75 * ahead.max())
            j = int(good[rng.integers(len(good))])
            p, theta = ends[j], float(head[j])
            spin = 1.0 if dth[j] >= 0 else -1.0
        else:
            theta += spin * max_turn
        theta = float(np.arctan2(np.sin(theta), np.cos(theta)))
        out[k] = (p[0], p[1], theta)
    return out


# --------------------------------------------------------------------------------------------
# Ray casting


def cast_rays(
    occ: np.ndarray,
    origins: np.ndarray,
    angles: np.ndarray,
    *,
    max_range: float | None = None,
    free: np.ndarray | None = None,
) -> np.ndarray:
    """Range of each ray to the first occupied pixel it enters (exact grid traversal).

    Rays are marched all at once: a ray far from any wall leaps by the free distance to the
    nearest occupied pixel (minus a safety margin); near walls it steps cell by cell
    (Amanatides & Woo's DDA), so the hit is the exact entry point into the occupied square.

    Args:
        occ: ``(H, W)`` bool occupancy image.
        origins: ``(M, 2)`` ray starts ``(x, y)`` in pixels.
        angles: ``(M,)`` ray directions in the map, radians.
        max_range: stop rays at this range (pixels); ``None`` for none.
        free: optional precomputed `free_distance` of ``occ``.

    Returns:
        ``(M,)`` float64 ranges in pixels; ``inf`` for rays that hit nothing (left the map or
        passed ``max_range``). A ray starting inside an occupied pixel has range 0.
    """
    occ = np.asarray(occ, dtype=bool)
    free = free_distance(occ) if free is None else free
    h, w = occ.shape
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 2)
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    limit = np.inf if max_range is None else float(max_range)
    m = len(angles)
    result = np.full(m, np.inf)
    dx, dy = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        inv_x, inv_y = 1.0 / np.abs(dx), 1.0 / np.abs(dy)
    sx = np.where(dx > 0, 1, -1)
    sy = np.where(dy > 0, 1, -1)
    ox, oy = origins[:, 0] + 0.5, origins[:, 1] + 0.5  # cell (c, r) covers [c, c+1) here
    cx, cy = np.floor(ox).astype(np.int64), np.floor(oy).astype(np.int64)
    t = np.zeros(m)

    def boundary(u: np.ndarray, c: np.ndarray, d: np.ndarray, inv: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return np.where(d == 0, np.inf, np.where(d > 0, c + 1 - u, u - c) * inv)

    tx, ty = boundary(ox, cx, dx, inv_x), boundary(oy, cy, dy, inv_y)
    idx = np.arange(m)
    inside = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
    start_hit = inside & occ[np.clip(cy, 0, h - 1), np.clip(cx, 0, w - 1)]
    result[start_hit] = 0.0
    keep = inside & ~start_hit
    arrays = [idx, ox, oy, dx, dy, inv_x, inv_y, sx, sy, cx, cy, t, tx, ty]
    arrays = [a[keep] for a in arrays]
    idx, ox, oy, dx, dy, inv_x, inv_y, sx, sy, cx, cy, t, tx, ty = arrays
    while len(idx):
        far = free[cy, cx] - 1.5
        leap = far >= _JUMP_MIN - 1.5
        if leap.any():
            # leap through free space: no occupied square is within `far` of the current point
            t = np.where(leap, t + far, t)
            ux, uy = ox + t * dx, oy + t * dy
            nx, ny = np.floor(ux).astype(np.int64), np.floor(uy).astype(np.int64)
            cx = np.where(leap, nx, cx)
            cy = np.where(leap, ny, cy)
            tx = np.where(leap, t + boundary(ux, nx, dx, inv_x), tx)
            ty = np.where(leap, t + boundary(uy, ny, dy, inv_y), ty)
        step = ~leap
        along_x = step & (tx < ty)
        along_y = step & ~along_x
        t = np.where(along_x, tx, np.where(along_y, ty, t))
        cx = cx + np.where(along_x, sx, 0)
        cy = cy + np.where(along_y, sy, 0)
        tx = np.where(along_x, tx + inv_x, tx)
        ty = np.where(along_y, ty + inv_y, ty)
        inside = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h) & (t <= limit)
        hit = inside & occ[np.clip(cy, 0, h - 1), np.clip(cx, 0, w - 1)]
        result[idx[hit]] = t[hit]
        keep = inside & ~hit
        if not keep.all():
            arrays = [a[keep] for a in (idx, ox, oy, dx, dy, inv_x, inv_y, sx, sy, cx, cy, t, tx, ty)]
            idx, ox, oy, dx, dy, inv_x, inv_y, sx, sy, cx, cy, t, tx, ty = arrays
    result[result > limit] = np.inf
    return result


def ray_angles(rays: int = 256, step_deg: float = DEFAULT_STEP_DEG) -> np.ndarray:
    """``(rays,)`` ray angles in the sensor frame, radians: ``0, step, 2 step, ...``."""
    return np.radians(step_deg) * np.arange(rays)


def scan_sequence(
    occ: np.ndarray,
    poses: np.ndarray,
    *,
    rays: int = 256,
    step_deg: float = DEFAULT_STEP_DEG,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
    max_range: float | None = None,
    free: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Scan from every pose at once; see `scan`.

    Args:
        poses: ``(K, 3)`` poses ``(x, y, theta)``, pixels and radians.

    Returns:
        ``K`` arrays ``(N_k, 2)`` float64 of points in each sensor's frame, pixels, in ray order.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if rays < 1:
        raise ConfigError(f"a scan needs at least 1 ray, got {rays}")
    if noise < 0:
        raise ConfigError(f"range noise must be non-negative, got {noise}")
    local = ray_angles(rays, step_deg)
    k = len(poses)
    origins = np.repeat(poses[:, :2], rays, axis=0)
    angles = (poses[:, 2:3] + local[None]).reshape(-1)
    r = cast_rays(occ, origins, angles, max_range=max_range, free=free).reshape(k, rays)
    if noise > 0:
        rng = np.random.default_rng() if rng is None else rng
        r = np.maximum(r + rng.normal(0.0, noise, r.shape), 0.0)
    dirs = np.stack([np.cos(local), np.sin(local)], -1)
    return [r_k[np.isfinite(r_k), None] * dirs[np.isfinite(r_k)] for r_k in r]


def scan(
    occ: np.ndarray,
    pose: np.ndarray,
    *,
    rays: int = 256,
    step_deg: float = DEFAULT_STEP_DEG,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
    max_range: float | None = None,
    free: np.ndarray | None = None,
) -> np.ndarray:
    """One lidar scan from ``pose``.

    Args:
        occ: ``(H, W)`` bool occupancy image.
        pose: ``(3,)`` sensor pose ``(x, y, theta)``, pixels and radians.
        rays: number of rays; ray ``i`` points at ``theta + i * step_deg`` in the map.
        step_deg: angle between rays, degrees.
        noise: standard deviation of Gaussian range noise, pixels (0 for none).
        rng: generator of the noise (a fresh unseeded one if ``None``).
        max_range: rays longer than this (pixels) return nothing; ``None`` for no limit.
        free: optional precomputed `free_distance` of ``occ`` (saves ~50 ms per call on a
            1024 x 1024 map).

    Returns:
        ``(N, 2)`` float64 points in the sensor frame (x along the heading), pixels,
        ``N <= rays`` (rays that hit nothing are dropped).
    """
    return scan_sequence(
        occ,
        np.asarray(pose)[None],
        rays=rays,
        step_deg=step_deg,
        noise=noise,
        rng=rng,
        max_range=max_range,
        free=free,
    )[0]


# --------------------------------------------------------------------------------------------
# Sequences


def simulate_2d(
    seed: int,
    *,
    frames: int = 256,
    rays: int = 256,
    noise: float = 0.0,
    map_seed: int | None = None,
    map_size: int = 1024,
    max_range: float | None = None,
) -> Sequence:
    """A simulated 2D lidar sequence: a seeded walk on a seeded map, scanned at every pose.

    The map is ``make_map(map_seed, size=map_size)`` (``map_seed`` defaults to ``seed``), so
    several trajectories over one map are ``simulate_2d(s, map_seed=m)`` for several ``s``;
    `sequence_map` rebuilds the map of a simulated sequence.

    Args:
        seed: seed of the trajectory and the noise.
        frames: number of frames K.
        rays: rays per scan, evenly spread over 360 degrees.
        noise: standard deviation of Gaussian range noise, pixels.
        map_seed: seed of the map (default ``seed``).
        map_size: map width and height, pixels.
        max_range: lidar range limit, pixels (``None``: unlimited, as in DeepMapping).

    Returns:
        A 2D `Sequence` in pixels: frames in the sensor frame, ground-truth SE(2) poses
        ``(K, 3, 3)`` local -> map, origins zero, ``meta`` with every parameter.
    """
    map_seed = seed if map_seed is None else map_seed
    occ, free = cached_map(int(map_seed), int(map_size))
    xyt = make_trajectory(occ, seed, frames=frames, free=free)
    step_deg = 360.0 / rays
    pts = scan_sequence(
        occ,
        xyt,
        rays=rays,
        step_deg=step_deg,
        noise=noise,
        rng=np.random.default_rng([int(seed), 2]),
        max_range=max_range,
        free=free,
    )
    return Sequence(
        frames=pts,
        name=f"sim2d-s{seed}-m{map_seed}",
        unit="px",
        poses=g.se2_from_xytheta(xyt),
        meta={
            "generator": "strep_core.sim.simulate_2d",
            "sensor": {"kind": "laser", "planar": True},
            "seed": int(seed),
            "map_seed": int(map_seed),
            "map_size": int(map_size),
            "rays": int(rays),
            "step_deg": step_deg,
            "noise": float(noise),
            "max_range": None if max_range is None else float(max_range),
        },
    )


def sequence_map(seq: Sequence) -> np.ndarray:
    """The occupancy image ``(size, size)`` behind a sequence made by `simulate_2d`.

    Raises:
        ConfigError: the sequence's ``meta`` has no ``map_seed`` / ``map_size``.
    """
    try:
        seed, size = int(seq.meta["map_seed"]), int(seq.meta["map_size"])  # type: ignore[call-overload]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"sequence {seq.name!r} was not made by simulate_2d (no map seed)") from exc
    return cached_map(seed, size)[0].copy()


def write_deepmapping(seq: Sequence, out_dir: str | Path) -> Path:
    """Write a 2D pixel sequence in DeepMapping's format, readable by `read_deepmapping`.

    Writes ``NNN.pcd`` (binary PCD, points in pixels / 512, z = 0; at least 3 digits) and,
    when the sequence has ground truth, ``gt_pose.mat`` with key ``pose``: ``(K, 3)``
    ``x, y`` in pixels and ``theta`` in radians.

    Returns:
        ``out_dir`` (created if missing).

    Raises:
        ConfigError: the sequence is not 2D or not in pixels.
    """
    from scipy.io import savemat

    if seq.dim != 2 or seq.unit != "px":
        raise ConfigError(f"DeepMapping's format holds 2D sequences in pixels, not {seq.dim}D in {seq.unit!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    digits = max(3, len(str(len(seq) - 1)))
    for i, f in enumerate(seq.frames):
        (out / f"{i:0{digits}d}.pcd").write_bytes(format_pcd(f / DEEPMAPPING_SCALE))
    if seq.poses is not None:
        savemat(out / "gt_pose.mat", {"pose": g.se2_to_xytheta(seq.poses)})
    return out
