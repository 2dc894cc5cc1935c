"""Floor plans for the 2D lidar simulator (`strep_core.sim.lidar2d`): seeded occupancy images of
rooms split by walls with doors, and the free-space distance the ray caster leaps by.

A map is a ``(size, size)`` bool image, ``True`` = occupied; pixel ``occ[r, c]`` is the unit
square centred on ``(x, y) = (c, r)`` in map pixels. The same seed gives a bit-identical map.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.ndimage import distance_transform_edt

from strep_core.errors import ConfigError


@dataclass(frozen=True)
class _Rect:
    """A half-open region of the map ``[x0, x1) x [y0, y1)`` in pixels."""

    x0: int
    y0: int
    x1: int
    y1: int


def _wall(occ: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> None:
    occ[max(y0, 0) : max(y1, 0), max(x0, 0) : max(x1, 0)] = True


def make_map(
    seed: int,
    *,
    size: int = 1024,
    wall: int = 3,
    min_room: int = 128,
    depth: int = 3,
    door: tuple[int, int] = (48, 96),
    partial_walls: float = 0.3,
    corridor: bool = True,
    boxes: int = 8,
) -> np.ndarray:
    """A seeded floor plan of rooms, doors, a corridor and free-standing boxes.

    The plan is a binary space partition of the square inside the outer walls: each split
    draws a wall (``wall`` px thick) with one or two door gaps; with probability
    ``partial_walls`` a split wall is only a stub (an open-plan room with a free-standing wall,
    like DeepMapping's maps). With ``corridor`` the first split is a long corridor 64-96 px
    wide, where pairwise alignment is ambiguous along its axis. Then ``boxes`` rectangles
    (12-60 px) are placed at least 48 px from every other wall, so no door is blocked.
    Every region is reachable from every other (each full wall has a door).

    Args:
        seed: the map's seed.
        size: width and height of the image in pixels.
        wall: wall thickness in pixels.
        min_room: smallest side of a room in pixels (regions are not split below twice it).
        depth: levels of the partition (up to ``2**depth`` rooms, plus the corridor).
        door: smallest and largest door width in pixels.
        partial_walls: probability that a split wall is a stub instead of a wall with doors.
        corridor: make the first split a corridor.
        boxes: number of free-standing boxes and pillars.

    Returns:
        ``(size, size)`` bool occupancy image, ``occ[y, x]``.

    Raises:
        ConfigError: a size too small for the walls and rooms asked for.
    """
    if size < 4 * wall + 2 * min_room or wall < 1 or door[0] < 1 or door[1] < door[0]:
        raise ConfigError(f"map size {size} px is too small for rooms of {min_room} px and walls of {wall} px")
    rng = np.random.default_rng([int(seed), 0])
    occ = np.zeros((size, size), dtype=bool)
    _wall(occ, 0, 0, size, wall)
    _wall(occ, 0, size - wall, size, size)
    _wall(occ, 0, 0, wall, size)
    _wall(occ, size - wall, 0, size, size)
    doors: list[tuple[int, int, int, int]] = []  # rectangles carved after all walls are drawn

    def split_wall(vertical: bool, pos: int, lo: int, hi: int, *, stub: float = partial_walls) -> None:
        """Draw a wall at ``pos`` (x if vertical, else y) spanning ``[lo, hi)``."""
        length = hi - lo
        if rng.random() < stub:
            frac = rng.uniform(0.3, 0.7)
            if rng.random() < 0.5:
                lo2, hi2 = lo, lo + int(frac * length)
            else:
                lo2, hi2 = hi - int(frac * length), hi
            if vertical:
                _wall(occ, pos, lo2, pos + wall, hi2)
            else:
                _wall(occ, lo2, pos, hi2, pos + wall)
            return
        if vertical:
            _wall(occ, pos, lo, pos + wall, hi)
        else:
            _wall(occ, lo, pos, hi, pos + wall)
        n_doors = 1 if length < 3 * min_room or rng.random() < 0.5 else 2
        for k in range(n_doors):
            width = int(rng.integers(door[0], door[1] + 1))
            seg_lo = lo + k * length // n_doors + wall
            seg_hi = lo + (k + 1) * length // n_doors - wall - width
            start = int(rng.integers(seg_lo, max(seg_hi, seg_lo) + 1))
            if vertical:
                doors.append((pos, start, pos + wall, start + width))
            else:
                doors.append((start, pos, start + width, pos + wall))

    def partition(r: _Rect, level: int) -> None:
        w, h = r.x1 - r.x0, r.y1 - r.y0
        if level >= depth or max(w, h) < 2 * min_room + wall:
            return
        if level > 0 and rng.random() < 0.15:
            return  # leave some large rooms
        vertical = w >= h if abs(w - h) > min_room // 2 else bool(rng.random() < 0.5)
        extent = w if vertical else h
        if extent < 2 * min_room + wall:
            vertical = not vertical
            extent = w if vertical else h
        start = r.x0 if vertical else r.y0
        pos = int(rng.integers(start + min_room, start + extent - min_room - wall + 1))
        lo, hi = (r.y0, r.y1) if vertical else (r.x0, r.x1)
        split_wall(vertical, pos, lo, hi)
        if vertical:
            partition(_Rect(r.x0, r.y0, pos, r.y1), level + 1)
            partition(_Rect(pos + wall, r.y0, r.x1, r.y1), level + 1)
        else:
            partition(_Rect(r.x0, r.y0, r.x1, pos), level + 1)
            partition(_Rect(r.x0, pos + wall, r.x1, r.y1), level + 1)

    inner = _Rect(wall, wall, size - wall, size - wall)
    extent = size - 2 * wall
    cw = int(rng.integers(64, 97))
    if corridor and extent >= 2 * min_room + cw + 2 * wall:
        vertical = bool(rng.random() < 0.5)
        a = int(rng.integers(wall + min_room, size - wall - min_room - cw - 2 * wall + 1))
        b = a + wall + cw  # the corridor is [a + wall, b) across, full length along
        for pos in (a, b):  # corridor walls always have doors: the corridor is the plan's spine
            split_wall(vertical, pos, wall, size - wall, stub=0.0)
        if vertical:
            partition(_Rect(wall, wall, a, size - wall), 1)
            partition(_Rect(b + wall, wall, size - wall, size - wall), 1)
        else:
            partition(_Rect(wall, wall, size - wall, a), 1)
            partition(_Rect(wall, b + wall, size - wall, size - wall), 1)
    else:
        partition(inner, 0)
    for x0, y0, x1, y1 in doors:
        occ[y0:y1, x0:x1] = False

    free = distance_transform_edt(~occ)
    placed: list[tuple[int, int, int, int]] = []
    for _ in range(50 * boxes):
        if len(placed) >= boxes:
            break
        bw, bh = (int(v) for v in rng.integers(12, 61, size=2))
        x0 = int(rng.integers(wall, size - wall - bw))
        y0 = int(rng.integers(wall, size - wall - bh))
        if free[y0 : y0 + bh, x0 : x0 + bw].min() < 48:
            continue
        gaps = [
            np.hypot(max(px0 - (x0 + bw), x0 - px1, 0), max(py0 - (y0 + bh), y0 - py1, 0))
            for px0, py0, px1, py1 in placed
        ]
        if min(gaps, default=np.inf) < 48:
            continue
        placed.append((x0, y0, x0 + bw, y0 + bh))
        occ[y0 : y0 + bh, x0 : x0 + bw] = True
    return occ


@lru_cache(maxsize=8)
def cached_map(seed: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """``make_map(seed, size=size)`` and its `free_distance`, read-only and cached (the 20
    benchmark trajectories share 3 maps)."""
    occ = make_map(seed, size=size)
    free = free_distance(occ)
    occ.flags.writeable = False
    free.flags.writeable = False
    return occ, free


def free_distance(occ: np.ndarray) -> np.ndarray:
    """``(H, W)`` float64: distance in pixels from each pixel centre to the nearest occupied one.

    Occupied pixels get 0. Pass it to `scan` / `scan_sequence` to reuse it between calls.
    """
    return np.asarray(distance_transform_edt(~np.asarray(occ, dtype=bool)), dtype=np.float64)
