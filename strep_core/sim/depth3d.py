"""A 3D depth-camera simulator in a procedural room, after the paper's Active Vision Dataset setting.

The Active Vision Dataset (AVD) photographs indoor scenes from camera positions on a
rectangular grid 300 mm apart, with 12 headings 30 degrees apart at each; the STREP paper
draws 16-frame trajectories from it and subsamples the depth images. Here:

* `make_room` builds a seeded room: floor, ceiling and four walls, furniture boxes against the
  walls and free-standing, a table on legs and flat frames on the walls. World frame: metres,
  ``z`` up, floor at ``z = 0``, the room spans ``[0, W] x [0, L] x [0, H]``.
* `make_trajectory_3d` walks on the 300 mm grid of free floor: each step moves to a
  neighbouring grid point or turns by +-30 degrees, so consecutive frames overlap.
* `render_depth` casts one ray per subsampled pixel of a Kinect-like pinhole camera
  (640 x 480, ``fx = fy = 575``: about 58 x 45 degrees) with Open3D's ``RaycastingScene``.

Camera frame: OpenCV (``x`` right, ``y`` down, ``z`` forward), metres; poses are
camera -> world ``(4, 4)``. Open3D is imported inside the functions that need it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

from strep_core.errors import ConfigError
from strep_core.sequence import Sequence

if TYPE_CHECKING:
    from strep_core._open3d import o3d

GRID = 0.3  # metres between AVD camera positions
HEADINGS = 12  # headings per position, 30 degrees apart


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size in pixels, focal lengths and principal point in pixels."""

    width: int = 640
    height: int = 480
    fx: float = 575.0
    fy: float = 575.0
    cx: float = 319.5
    cy: float = 239.5

    def rays(self, stride: int) -> np.ndarray:
        """``(N, 3)`` ray directions in the camera frame with ``z = 1``, one per ``stride`` px.

        Pixels are sampled at ``stride // 2 + stride * i`` along each axis (row-major).
        """
        if stride < 1:
            raise ConfigError(f"pixel stride must be at least 1, got {stride}")
        u = np.arange(stride // 2, self.width, stride, dtype=np.float64)
        v = np.arange(stride // 2, self.height, stride, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        x = (uu.ravel() - self.cx) / self.fx
        y = (vv.ravel() - self.cy) / self.fy
        return np.stack([x, y, np.ones_like(x)], -1)


@dataclass(frozen=True)
class Room:
    """A closed room as a triangle mesh, with its furniture footprints.

    Attributes:
        size: ``(3,)`` room extent ``(W, L, H)`` in metres; the inside is ``[0, W] x [0, L] x [0, H]``.
        vertices: ``(V, 3)`` float64 mesh vertices, metres, world frame (``z`` up).
        triangles: ``(T, 3)`` int64 vertex indices (boxes; face orientation is not meaningful).
        obstacles: ``(B, 2, 2)`` floor footprints ``[[x0, y0], [x1, y1]]`` of everything that
            stands on the floor, metres.
        seed: the seed it was made from.
    """

    size: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    obstacles: np.ndarray
    seed: int


_BOX_TRIS = np.array(
    [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
     [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]],
    dtype=np.int64,
)  # fmt: skip


def _box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(8, 3)`` and triangles ``(12, 3)`` of the axis-aligned box ``[lo, hi]``."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array(
        [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
         [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]],
        dtype=np.float64,
    )  # fmt: skip
    return v, _BOX_TRIS


def make_room(
    seed: int,
    *,
    size: tuple[float, float] = (4.0, 7.0),
    height: tuple[float, float] = (2.5, 3.0),
    furniture: tuple[int, int] = (4, 7),
    table: bool = True,
    frames_on_walls: int = 4,
) -> Room:
    """A seeded furnished room.

    Args:
        seed: the room's seed.
        size: range of the floor's width and length, metres (each drawn uniformly).
        height: range of the ceiling height, metres.
        furniture: range of the number of furniture boxes (cabinets and shelves against the
            walls, 0.3-0.6 m deep, 0.6-1.8 m wide, 0.5-2.0 m high; beds, sofas and crates
            free-standing, 0.5-2.0 m wide, 0.4-1.0 m high).
        table: add a table (0.04 m top at 0.72 m, four 5 cm legs).
        frames_on_walls: number of flat frames (pictures, boards: 3 cm deep) on the walls.

    Returns:
        The `Room`; walls, floor and ceiling are 0.1 m thick boxes outside the inner space.
    """
    rng = np.random.default_rng([int(seed), 4])
    w, ln = (float(v) for v in rng.uniform(size[0], size[1], 2))
    h = float(rng.uniform(*height))
    th = 0.1
    boxes: list[tuple[np.ndarray, np.ndarray]] = [
        (np.array([-th, -th, -th]), np.array([w + th, ln + th, 0.0])),  # floor
        (np.array([-th, -th, h]), np.array([w + th, ln + th, h + th])),  # ceiling
        (np.array([-th, -th, 0.0]), np.array([0.0, ln + th, h])),  # wall x = 0
        (np.array([w, -th, 0.0]), np.array([w + th, ln + th, h])),  # wall x = W
        (np.array([0.0, -th, 0.0]), np.array([w, 0.0, h])),  # wall y = 0
        (np.array([0.0, ln, 0.0]), np.array([w, ln + th, h])),  # wall y = L
    ]
    footprints: list[np.ndarray] = []

    def fits(lo: np.ndarray, hi: np.ndarray, gap: float) -> bool:
        return all(
            lo[0] >= f[1, 0] + gap or hi[0] <= f[0, 0] - gap or lo[1] >= f[1, 1] + gap or hi[1] <= f[0, 1] - gap
            for f in footprints
        )

    n_furniture = int(rng.integers(furniture[0], furniture[1] + 1))
    for _ in range(40 * n_furniture):
        if len(footprints) >= n_furniture:
            break
        if rng.random() < 0.5:  # against a wall
            width, depth, tall = rng.uniform(0.6, 1.8), rng.uniform(0.3, 0.6), rng.uniform(0.5, 2.0)
            side = int(rng.integers(4))
            along = (w if side < 2 else ln) - width
            if along <= 0:
                continue
            a = rng.uniform(0.0, along)
            if side == 0:
                lo, hi = np.array([a, 0.0]), np.array([a + width, depth])
            elif side == 1:
                lo, hi = np.array([a, ln - depth]), np.array([a + width, ln])
            elif side == 2:
                lo, hi = np.array([0.0, a]), np.array([depth, a + width])
            else:
                lo, hi = np.array([w - depth, a]), np.array([w, a + width])
        else:  # free-standing
            sx, sy, tall = rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), rng.uniform(0.4, 1.0)
            if sx > w - 1.2 or sy > ln - 1.2:
                continue
            x, y = rng.uniform(0.6, w - 0.6 - sx), rng.uniform(0.6, ln - 0.6 - sy)
            lo, hi = np.array([x, y]), np.array([x + sx, y + sy])
        if not fits(lo, hi, 0.6):
            continue
        footprints.append(np.stack([lo, hi]))
        boxes.append((np.append(lo, 0.0), np.append(hi, tall)))
    if table:
        for _ in range(40):
            tx, ty = rng.uniform(0.8, 1.2), rng.uniform(0.7, 0.9)
            if w < tx + 1.6 or ln < ty + 1.6:
                break
            x, y = rng.uniform(0.8, w - 0.8 - tx), rng.uniform(0.8, ln - 0.8 - ty)
            lo, hi = np.array([x, y]), np.array([x + tx, y + ty])
            if not fits(lo, hi, 0.6):
                continue
            footprints.append(np.stack([lo, hi]))
            boxes.append((np.array([x, y, 0.72]), np.array([x + tx, y + ty, 0.76])))
            for cx, cy in ((x, y), (x + tx - 0.05, y), (x, y + ty - 0.05), (x + tx - 0.05, y + ty - 0.05)):
                boxes.append((np.array([cx, cy, 0.0]), np.array([cx + 0.05, cy + 0.05, 0.72])))
            break
    for _ in range(frames_on_walls):
        fw, fh = rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.9)
        z = rng.uniform(1.0, max(1.0, h - 0.3 - fh))
        side = int(rng.integers(4))
        a = rng.uniform(0.1, max(0.1, (w if side < 2 else ln) - fw - 0.1))
        d = 0.03
        lo, hi = {
            0: (np.array([a, 0.0, z]), np.array([a + fw, d, z + fh])),
            1: (np.array([a, ln - d, z]), np.array([a + fw, ln, z + fh])),
            2: (np.array([0.0, a, z]), np.array([d, a + fw, z + fh])),
            3: (np.array([w - d, a, z]), np.array([w, a + fw, z + fh])),
        }[side]
        boxes.append((lo, hi))
    verts, tris = [], []
    for i, (lo, hi) in enumerate(boxes):
        v, t = _box(lo, hi)
        verts.append(v)
        tris.append(t + 8 * i)
    return Room(
        size=np.array([w, ln, h]),
        vertices=np.concatenate(verts),
        triangles=np.concatenate(tris),
        obstacles=np.array(footprints, dtype=np.float64).reshape(-1, 2, 2),
        seed=int(seed),
    )


def raycasting_scene(room: Room) -> o3d.t.geometry.RaycastingScene:
    """An Open3D ``RaycastingScene`` holding the room's mesh (for `render_depth` and distances)."""
    from strep_core._open3d import o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(_tensor(room.vertices.astype(np.float32)), _tensor(room.triangles.astype(np.uint32)))
    return scene


def free_grid(room: Room, *, grid: float = GRID, wall_clearance: float = 0.3, clearance: float = 0.25) -> np.ndarray:
    """``(I, J)`` bool: which points ``(grid / 2 + i grid, grid / 2 + j grid)`` of the floor are free.

    A point is free when it is at least ``wall_clearance`` metres from the walls and
    ``clearance`` metres from every furniture footprint.
    """
    w, ln = float(room.size[0]), float(room.size[1])
    xs = grid / 2 + grid * np.arange(int(np.floor((w - grid / 2) / grid)) + 1)
    ys = grid / 2 + grid * np.arange(int(np.floor((ln - grid / 2) / grid)) + 1)
    px, py = np.meshgrid(xs, ys, indexing="ij")
    ok = (px >= wall_clearance) & (px <= w - wall_clearance)
    ok &= (py >= wall_clearance) & (py <= ln - wall_clearance)
    for f in room.obstacles:
        dx = np.maximum(np.maximum(f[0, 0] - px, px - f[1, 0]), 0.0)
        dy = np.maximum(np.maximum(f[0, 1] - py, py - f[1, 1]), 0.0)
        ok &= np.hypot(dx, dy) >= clearance
    return ok


def camera_pose(position: np.ndarray, heading: float) -> np.ndarray:
    """Camera -> world ``(4, 4)`` of a level camera at ``position (3,)`` looking along ``heading``.

    ``heading`` (radians) is measured in the floor plane from the world ``x`` axis towards ``y``;
    the camera's ``z`` (forward) is ``(cos h, sin h, 0)``, its ``y`` (down) is ``-z_world``.
    """
    c, s = np.cos(heading), np.sin(heading)
    out = np.eye(4)
    out[:3, 0] = (s, -c, 0.0)  # right
    out[:3, 1] = (0.0, 0.0, -1.0)  # down
    out[:3, 2] = (c, s, 0.0)  # forward
    out[:3, 3] = position
    return out


def _tensor(a: np.ndarray) -> o3d.core.Tensor:
    """An Open3D tensor holding its own copy of ``a``."""
    from strep_core._open3d import o3d

    return o3d.core.Tensor.from_numpy(np.ascontiguousarray(a)).clone()


def _view_depth(scene: Any, positions: np.ndarray, headings: np.ndarray, camera: Camera) -> np.ndarray:
    """Median range (m) over a level fan of 9 rays across the field of view, per view.

    Args:
        positions: ``(M, 3)`` camera centres, world.
        headings: ``(M,)`` headings, radians.
    """
    half = np.arctan2(camera.width / 2, camera.fx)
    ang = headings[:, None] + np.linspace(-half, half, 9)[None]
    d = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
    o = np.broadcast_to(positions[:, None, :], d.shape)
    rays = np.concatenate([o, d], -1).reshape(-1, 6).astype(np.float32)
    t = scene.cast_rays(_tensor(rays))["t_hit"].numpy().reshape(len(headings), -1)
    return np.median(t, axis=1)


def make_trajectory_3d(
    room: Room,
    seed: int,
    *,
    frames: int = 16,
    camera_height: float = 1.0,
    camera: Camera | None = None,
    min_view: float = 1.0,
    scene: Any = None,
) -> np.ndarray:
    """A seeded walk of a level camera on the room's 300 mm grid, headings 30 degrees apart.

    Each step either moves to a free 4-neighbour of the grid point (heading kept) or turns by
    +-30 degrees in place, with equal odds, never undoing the previous step; states whose
    view is blocked (median range across the field of view below ``min_view`` metres) are
    avoided while others are possible.

    Args:
        room: the room.
        seed: the trajectory's seed.
        frames: number of poses K.
        camera_height: height of the optical centre above the floor, metres.
        camera: the camera (default `Camera()`), for the field of view.
        min_view: smallest acceptable median range ahead, metres.
        scene: optional `raycasting_scene` of ``room``, reused.

    Returns:
        ``(K, 4, 4)`` camera -> world poses.

    Raises:
        ConfigError: the room has no free grid point.
    """
    camera = Camera() if camera is None else camera
    scene = raycasting_scene(room) if scene is None else scene
    rng = np.random.default_rng([int(seed), 3])
    free = free_grid(room)
    cells = np.argwhere(free)
    if len(cells) == 0:
        raise ConfigError(f"room {room.seed} has no free grid point for the camera")
    steps = 2.0 * np.pi / HEADINGS

    def position(i: int, j: int) -> np.ndarray:
        return np.array([GRID / 2 + GRID * i, GRID / 2 + GRID * j, camera_height])

    # start where the view is open
    order = rng.permutation(len(cells))
    state = (int(cells[order[0]][0]), int(cells[order[0]][1]), int(rng.integers(HEADINGS)))
    for c in order[:32]:
        hs = rng.permutation(HEADINGS)
        depth = _view_depth(scene, np.tile(position(*cells[c]), (HEADINGS, 1)), hs * steps, camera)
        if depth.max() >= 1.5 * min_view:
            state = (int(cells[c][0]), int(cells[c][1]), int(hs[int(np.argmax(depth))]))
            break
    out = [state]
    last: tuple[int, int, int] = (0, 0, 0)
    for _ in range(1, frames):
        i, j, hd = state
        moves = [
            (di, dj, 0)
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= i + di < free.shape[0] and 0 <= j + dj < free.shape[1] and free[i + di, j + dj]
        ]
        turns = [(0, 0, 1), (0, 0, -1)]
        undo = (-last[0], -last[1], -last[2])
        moves = [m for m in moves if m != undo]
        turns = [t for t in turns if t != undo]
        cand = [(i + m[0], j + m[1], hd) for m in moves] + [(i, j, (hd + t[2]) % HEADINGS) for t in turns]
        deltas = moves + turns
        weights = np.array([0.5 / max(len(moves), 1)] * len(moves) + [0.5 / len(turns)] * len(turns))
        where = np.stack([position(c[0], c[1]) for c in cand])
        depth = _view_depth(scene, where, np.array([c[2] * steps for c in cand]), camera)
        open_view = depth >= min_view
        if open_view.any():
            weights = weights * open_view
        k = int(rng.choice(len(cand), p=weights / weights.sum()))
        state, last = cand[k], deltas[k]
        out.append(state)
    return np.stack([camera_pose(position(i, j), hd * steps) for i, j, hd in out])


def render_depth(
    scene: Any,
    pose: np.ndarray,
    *,
    camera: Camera | None = None,
    stride: int = 12,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
    max_depth: float | None = None,
) -> np.ndarray:
    """Points seen by a depth camera, one per ``stride``-th pixel along rows and columns.

    Args:
        scene: a `raycasting_scene`.
        pose: ``(4, 4)`` camera -> world.
        camera: the pinhole camera (default `Camera()`).
        stride: pixel stride of the subsampling (12 gives 53 x 40 = 2120 rays at 640 x 480).
        noise: standard deviation of Gaussian depth noise, metres (along each ray, so the
            noisy point stays on its pixel's ray).
        rng: generator of the noise (a fresh unseeded one if ``None``).
        max_depth: drop points deeper than this (metres); ``None`` for no limit.

    Returns:
        ``(N, 3)`` float64 points in the camera frame (OpenCV: x right, y down, z forward),
        metres, in pixel order; rays that hit nothing are dropped.
    """

    camera = Camera() if camera is None else camera
    d_cam = camera.rays(stride)
    rot, t = pose[:3, :3], pose[:3, 3]
    rays = np.concatenate([np.broadcast_to(t, d_cam.shape), d_cam @ rot.T], 1).astype(np.float32)
    depth = scene.cast_rays(_tensor(rays))["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(depth)
    if max_depth is not None:
        ok &= depth <= max_depth
    depth, d_cam = depth[ok], d_cam[ok]
    if noise > 0:
        rng = np.random.default_rng() if rng is None else rng
        depth = np.maximum(depth + rng.normal(0.0, noise, depth.shape), 1e-3)
    return depth[:, None] * d_cam


@lru_cache(maxsize=4)
def _cached_room(seed: int) -> Room:
    room = make_room(seed)
    for a in (room.size, room.vertices, room.triangles, room.obstacles):
        a.flags.writeable = False
    return room


def simulate_3d(
    seed: int,
    *,
    frames: int = 16,
    stride: int = 12,
    noise: float = 0.0,
    room_seed: int | None = None,
    camera_height: float = 1.0,
    max_depth: float | None = None,
) -> Sequence:
    """A simulated 3D depth sequence: a seeded AVD-like walk in a seeded room.

    Args:
        seed: seed of the trajectory and the noise.
        frames: number of frames K (16 in the paper).
        stride: pixel stride of the depth subsampling (12: up to 2120 points per frame).
        noise: standard deviation of Gaussian depth noise, metres.
        room_seed: seed of the room (default ``seed``); `sequence_room` rebuilds it.
        camera_height: camera height above the floor, metres.
        max_depth: depth range limit, metres (``None``: unlimited; the room is closed).

    Returns:
        A 3D `Sequence` in metres: frames in the camera frame (OpenCV axes), ground-truth
        camera -> world poses ``(K, 4, 4)``, origins zero, ``meta`` with every parameter.
    """
    if noise < 0:
        raise ConfigError(f"depth noise must be non-negative, got {noise}")
    room_seed = seed if room_seed is None else room_seed
    room = _cached_room(int(room_seed))
    scene = raycasting_scene(room)
    camera = Camera()
    poses = make_trajectory_3d(room, seed, frames=frames, camera_height=camera_height, scene=scene)
    rng = np.random.default_rng([int(seed), 5])
    pts = [
        render_depth(scene, p, camera=camera, stride=stride, noise=noise, rng=rng, max_depth=max_depth) for p in poses
    ]
    return Sequence(
        frames=pts,
        name=f"sim3d-s{seed}-r{room_seed}",
        unit="m",
        poses=poses,
        meta={
            "generator": "strep_core.sim.simulate_3d",
            "sensor": {"kind": "depth", "axes": "opencv", "vertical_axis": [0.0, -1.0, 0.0]},
            "seed": int(seed),
            "room_seed": int(room_seed),
            "stride": int(stride),
            "noise": float(noise),
            "camera_height": float(camera_height),
            "max_depth": None if max_depth is None else float(max_depth),
            "camera": asdict(camera),
            "grid_m": GRID,
            "heading_step_deg": 360.0 / HEADINGS,
        },
    )


def sequence_room(seq: Sequence) -> Room:
    """The `Room` behind a sequence made by `simulate_3d`.

    Raises:
        ConfigError: the sequence's ``meta`` has no ``room_seed``.
    """
    try:
        seed = int(seq.meta["room_seed"])  # type: ignore[call-overload]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"sequence {seq.name!r} was not made by simulate_3d (no room seed)") from exc
    return _cached_room(seed)
