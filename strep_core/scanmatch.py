"""Global 2D scan matching: branch and bound over every heading and a window of translations.

After Olson ("Real-time correlative scan matching", ICRA 2009: a likelihood field and a
multi-resolution search with exact upper bounds) and Hess et al. (Cartographer, ICRA 2016:
precomputed max-pooled grids, one per depth of a branch and bound). The target scan becomes a
likelihood field ``exp(-d^2 / 2 sigma^2)`` on a grid of cell ``resolution`` (``d``: distance to
the nearest target point's cell centre; separable max-product, no distance transform); a
candidate pose scores the mean field value under the source's transformed points. Leaves are
every yaw ``k * yaw_step`` of the window (the full circle by default) and every translation
cell within ``+-window`` of the guess.

Branch and bound over (yaw, x, y): a node at depth L covers ``2^L x 2^L`` translation cells and
``yaw_group(L)`` consecutive yaws. Its upper bound is the mean, over the source points rotated
by the group's centre yaw, of a grid max-pooled over the node's translation box widened by the
farthest such point's displacement under the group's yaw spread (``dilation``): no leaf below
the node can score higher. Nodes are expanded depth by depth (numpy batches, not one node at
a time); nodes whose bound does not exceed the best leaf found so far (greedy descents from the
best nodes of each depth) are pruned. At most ``max_nodes`` nodes go on per depth (the best
bounds): the search is exact while that cap is not reached (`MatchResult.exact`).

Conventions: 2D points ``(N, 2)``, poses ``(3, 3)`` SE(2), source -> target
(``p_target = T p_source``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from strep_core.voxels import first_per_cell

_Q = 255  # fields are stored as uint8: value * 255


@dataclass(frozen=True)
class ScanMatchParams:
    """Search window and grid (lengths in the sequence's unit, angles in radians).

    Attributes:
        window: translations up to this far from the guess's, along each axis.
        resolution: finest grid cell.
        yaw_step: finest yaw step.
        yaw_window: yaws up to this far from the guess's (``pi``: the full circle).
        sigma: width of the likelihood field.
        max_range: source points farther than this from the sensor are not used.
        max_points: at most this many source points (after a voxel grid of 2 cells).
        depth: translation depths of the branch and bound (top boxes of ``2^depth`` cells).
        max_nodes: cap on the nodes expanded per depth.
        seeds: greedy descents from this many of the best nodes of each depth (lower bounds).
        prior_weight, prior_scale: score lost at a distance ``prior_scale`` from the prior
            translation given to `ScanMatcher.match` (quadratic; 0: no prior).
    """

    window: float
    resolution: float
    yaw_step: float = float(np.radians(1.0))
    yaw_window: float = float(np.pi)
    sigma: float = 0.0
    max_range: float = float("inf")
    max_points: int = 150
    depth: int = 5
    max_nodes: int = 6000
    seeds: int = 16
    prior_weight: float = 0.0
    prior_scale: float = 1.0

    @property
    def field_sigma(self) -> float:
        return self.sigma if self.sigma > 0 else 2.0 * self.resolution


@dataclass(frozen=True)
class MatchResult:
    """Best pose found: ``pose`` ``(3, 3)``, ``score`` (mean likelihood, 0 to 1), the number of
    nodes scored, and ``exact``: no depth hit ``max_nodes`` (the result is the true optimum on the
    grid)."""

    pose: np.ndarray
    score: float
    nodes: int
    exact: bool


def _dilate(a: np.ndarray, width: int, axis: int) -> np.ndarray:
    """The max over every window of ``width`` cells along ``axis``, zero beyond ``a``: the full
    result, ``width - 1`` cells longer than ``a`` at each end (``out[m]`` is the max of
    ``a[m - width + 1 .. m]``); one zero border, then sparse doubling."""
    if width <= 1:
        return a
    pad = [(0, 0), (0, 0)]
    pad[axis] = (width - 1, width - 1)
    b, span = np.pad(a, pad), 1
    n = a.shape[axis] + width - 1  # the result's length along the axis

    def part(start: int, stop: int) -> tuple[slice, ...]:
        return (slice(start, stop),) if axis == 0 else (slice(None), slice(start, stop))

    while 2 * span <= width:
        b = np.maximum(b[part(0, b.shape[axis] - span)], b[part(span, None)])
        span *= 2
    return np.maximum(b[part(0, n)], b[part(width - span, width - span + n)])


def _rot(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _subsample(points: np.ndarray, cell: float, max_points: int) -> np.ndarray:
    """One point per ``cell`` voxel (the first), then at most ``max_points`` evenly spread."""
    pts = points[first_per_cell(points, cell)]
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).round().astype(int)]
    return pts


class ScanMatcher:
    """A target scan prepared for `match` (grids depend on the source's reach, set by params)."""

    def __init__(self, target: np.ndarray, params: ScanMatchParams, *, center: np.ndarray | None = None) -> None:
        self.params = p = params
        self.center = np.zeros(2) if center is None else np.asarray(center, dtype=np.float64)
        res = p.resolution
        self.w = int(np.ceil(p.window / res))
        # yaws: the full circle, or +-yaw_window around the guess's
        self.n_yaw = max(1, round(2 * min(p.yaw_window, np.pi) / p.yaw_step))
        self.depth = max(0, min(p.depth, int(np.ceil(np.log2(2 * self.w + 1)))))
        reach = p.max_range if np.isfinite(p.max_range) else 1e9
        self._reach_cells = int(np.ceil(reach / res))
        target = np.asarray(target, dtype=np.float64)[:, :2]
        self._target = target
        self._grids: dict[int, tuple[np.ndarray, int]] = {}

    # ---- grids

    def _build(self, src_cells: int, *, pooled: bool = True) -> None:
        """The field for sources reaching ``src_cells`` cells, and (``pooled``) its pooled grids.

        Only the target's block of the grid (its cells plus the field's and the pooling's
        reach) is computed; the rest is zero and stays untouched: the grids span the source's
        reach around the centre, far more than a submap covers (freiburg-079: 3,400 cells a
        side against about 1,400 x 700 of target; docs/design/laser-slam.md)."""
        p, res = self.params, self.params.resolution
        sig = p.field_sigma / res
        rad = int(np.ceil(3 * sig))
        self.dil = [self._dilation(L, src_cells) for L in range(self.depth + 1)]
        # leaves and nodes sample within src_cells + w of the centre: the field beyond is never read
        half = src_cells + self.w + 1
        self.half = half
        size = 2 * half + 1
        cells = np.rint((self._target - self.center) / res).astype(np.int64) + half
        ok = (cells >= -rad).all(1) & (cells < size + rad).all(1)
        cells = cells[ok]
        field = np.zeros((size, size), dtype=np.uint8)
        self._block: tuple[np.ndarray, np.ndarray] | None = None
        if len(cells):
            lo = np.maximum(cells.min(0) - rad, 0)
            hi = np.minimum(cells.max(0) + rad + 1, size)
            c = cells[((cells >= lo) & (cells < hi)).all(1)]
            key = np.unique(c[:, 0] * size + c[:, 1])
            c = np.column_stack([key // size, key % size])
            # the separable max-product (rows, then columns, each truncated to uint8) of an
            # occupancy is, cell by cell, the max of one stamp per occupied cell: the same numbers
            k = np.exp(-0.5 * (np.arange(-rad, rad + 1) / sig) ** 2)
            luts = [(np.arange(_Q + 1, dtype=np.float32) * ks).astype(np.uint8) for ks in k]
            stamp = np.array([[lut_t[lut_s[_Q]] for lut_t in luts] for lut_s in luts], dtype=np.uint8)
            d = np.arange(-rad, rad + 1)
            if (c >= rad).all() and (c < size - rad).all():  # every stamp inside the grid
                flat = (key[:, None] + (d[:, None] * size + d[None, :]).ravel()[None, :]).ravel()
                np.maximum.at(field.ravel(), flat, np.broadcast_to(stamp.ravel(), (len(key), stamp.size)).ravel())
            else:
                rows = (c[:, 0, None, None] + d[None, :, None]) + np.zeros((1, 1, len(d)), np.int64)
                cols = (c[:, 1, None, None] + d[None, None, :]) + np.zeros((1, len(d), 1), np.int64)
                vals = np.broadcast_to(stamp, rows.shape)
                ok = (rows >= 0) & (rows < size) & (cols >= 0) & (cols < size)
                np.maximum.at(field.ravel(), rows[ok] * size + cols[ok], vals[ok])
            self._block = (field[lo[0] : hi[0], lo[1] : hi[1]], lo)
            self._level = (self._block[0], lo)  # the last pooled depth's block and its origin: the field's
        self.grids = [field]
        self.flat = [field.ravel()]
        self.size = size
        self.src_cells = src_cells
        if pooled:
            self._pool()

    def _pool(self) -> None:
        """The max-pooled grids of every depth, computed over the target's block only: a pooled
        cell is nonzero only where its box, widened by the dilation, reaches the block. Each
        depth pools the one before over the difference of their boxes (a max over ``[lo, hi]``
        is a max over ``[lo', hi']`` of a max over ``[lo - lo', hi - hi']``): exact, and
        shorter windows than pooling the field at every depth (docs/design/laser-slam.md,
        round 11)."""
        size = self.size
        for L in range(len(self.grids), self.depth + 1):
            pooled = np.zeros((size, size), dtype=np.uint8)
            if self._block is not None:
                prev, at_prev = self._level
                (lo_prev, hi_prev), (lo_, hi_) = self._box(L - 1), self._box(L)
                # cell at_prev + i of the previous depth's block is the window's output index i + d_hi
                d_lo, d_hi = lo_ - lo_prev, hi_ - hi_prev
                block = _dilate(_dilate(prev, d_hi - d_lo + 1, 0), d_hi - d_lo + 1, 1)
                at = at_prev - d_hi
                self._level = (block, at)
                a = np.maximum(at, 0)
                b = np.minimum(at + np.array(block.shape), size)
                if (b > a).all():
                    pooled[a[0] : b[0], a[1] : b[1]] = block[a[0] - at[0] : b[0] - at[0], a[1] - at[1] : b[1] - at[1]]
            self.grids.append(pooled)
            self.flat.append(pooled.ravel())

    def _box(self, L: int) -> tuple[int, int]:
        """The cells a depth-L node's bound pools along each axis, from its box's corner: the
        box widened by the depth's dilation."""
        return -self.dil[L], (1 << L) - 1 + self.dil[L]

    def _yaw_group(self, L: int) -> int:
        """Yaws per node at depth L: the group doubles with the box from depth 2 on."""
        return 1 if L <= 1 else min(1 << (L - 1), self.n_yaw)

    def _dilation(self, L: int, src_cells: int) -> int:
        g = self._yaw_group(L)
        if g <= 1:
            return 0
        spread = 0.5 * (g - 1) * self.params.yaw_step
        return int(np.ceil(src_cells * spread)) + 1

    # ---- search

    def match(
        self,
        source: np.ndarray,
        guess: np.ndarray | None = None,
        *,
        prior: np.ndarray | None = None,
        yaw_cost: Callable[[np.ndarray], np.ndarray] | None = None,
        exclude: tuple[np.ndarray, float] | None = None,
        at_least: float = 0.0,
    ) -> MatchResult:
        """The best source -> target pose on the grid, within the window around ``guess``.

        ``prior``: ``(2,)`` expected translation; candidates lose ``prior_weight * (|t - prior| /
        prior_scale)^2`` of score (the bounds lose the least penalty over each node's box);
        ``yaw_cost``: score lost at each heading (radians in, array out; a node loses the least
        over its yaws); ``exclude``: ``(translation (2,), radius)``, no leaf within it at any
        heading (the runner-up of a search whose best lies there; a node whose box lies inside
        is dropped, one that reaches out keeps its bound); ``at_least``: only leaves scoring
        above this count, so nodes bounded at or below it are pruned from the start (a search
        that is of use only above a score; none found: the guess with score 0)."""
        p, res = self.params, self.params.resolution
        guess = np.eye(3) if guess is None else np.asarray(guess, dtype=np.float64)
        src = np.asarray(source, dtype=np.float64)[:, :2]
        src = src[np.linalg.norm(src, axis=1) <= p.max_range]
        if len(src) < 3:
            return MatchResult(guess, 0.0, 0, True)
        src = _subsample(src, 2 * res, p.max_points)
        src_cells = int(np.ceil(np.linalg.norm(src, axis=1).max() / res)) + 1
        if not self._grids_ready(src_cells):
            self._build(src_cells)
        elif len(self.grids) <= self.depth:
            self._pool()
        n_pts = len(src)
        yaw0 = float(np.arctan2(guess[1, 0], guess[0, 0]))
        yaws = yaw0 + p.yaw_step * (np.arange(self.n_yaw) - self.n_yaw // 2)
        t0 = guess[:2, 2] - self.center
        half, size = self.half, self.size

        cache: dict[int, np.ndarray] = {}

        def point_cells(L: int) -> np.ndarray:
            """``(groups, N)`` flat cell indices of the points at each group's centre yaw."""
            if L not in cache:
                g = self._yaw_group(L)
                n_groups = -(-self.n_yaw // g)
                centre = yaws[0] + p.yaw_step * (np.arange(n_groups) * g + 0.5 * (min(g, self.n_yaw) - 1))
                cs, sn = np.cos(centre)[:, None], np.sin(centre)[:, None]
                cx = np.rint((cs * src[:, 0] - sn * src[:, 1] + t0[0]) / res).astype(np.int32) + half
                cy = np.rint((sn * src[:, 0] + cs * src[:, 1] + t0[1]) / res).astype(np.int32) + half
                cache[L] = cx * size + cy
            return cache[L]

        if prior is not None and p.prior_weight > 0:
            pc = (np.asarray(prior, dtype=np.float64)[:2] - self.center - t0) / res  # prior in offset cells
            gain = p.prior_weight * _Q * n_pts * (res / p.prior_scale) ** 2
        else:
            pc, gain = None, 0.0
        yaw_pen: dict[int, np.ndarray] = {}
        if yaw_cost is not None:
            cost = np.ceil(_Q * n_pts * np.maximum(np.asarray(yaw_cost(yaws), dtype=np.float64), 0.0))
            for L in range(self.depth + 1):
                yaw_pen[L] = np.minimum.reduceat(cost, np.arange(0, self.n_yaw, self._yaw_group(L))).astype(np.int64)

        if exclude is not None:  # the excluded disc in offset cells
            ex_c = (np.asarray(exclude[0], dtype=np.float64)[:2] - self.center - t0) / res
            ex_r2 = (float(exclude[1]) / res) ** 2

        # a node's sum of uint8 fits 16 bits up to 257 points: summed at half the memory traffic
        acc = np.uint16 if n_pts * _Q <= np.iinfo(np.uint16).max else np.int64

        def score(L: int, yg: np.ndarray, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
            idx = point_cells(L)[yg] + (ox * size + oy).astype(np.int32)[:, None]
            out = np.take(self.flat[L], idx).sum(1, dtype=acc).astype(np.int64)
            if yaw_pen:
                out = out - yaw_pen[L][yg]
            if exclude is not None:  # the box's farthest corner from the disc's centre inside it
                hi = (1 << L) - 1
                fx = np.maximum(np.abs(ox - ex_c[0]), np.abs(ox + hi - ex_c[0]))
                fy = np.maximum(np.abs(oy - ex_c[1]), np.abs(oy + hi - ex_c[1]))
                out = np.where(fx * fx + fy * fy <= ex_r2, -1, out)
            if pc is None:
                return out
            hi = (1 << L) - 1
            dx = np.maximum(0, np.maximum(ox - pc[0], pc[0] - (ox + hi)))
            dy = np.maximum(0, np.maximum(oy - pc[1], pc[1] - (oy + hi)))
            return out - np.ceil(gain * (dx * dx + dy * dy)).astype(np.int64)

        top = self.depth
        step = 1 << top
        offs = np.arange(-self.w, self.w + 1, step)
        n_groups = -(-self.n_yaw // self._yaw_group(top))
        yg, ox, oy = (a.ravel() for a in np.meshgrid(np.arange(n_groups), offs, offs, indexing="ij"))
        bound = score(top, yg, ox, oy)
        nodes = len(bound)
        floor = int(np.floor(at_least * _Q * n_pts)) if at_least > 0 else -1
        best = (floor, 0, 0, 0)  # leaf score, yaw index, ox, oy
        exact = True

        def children(L: int, yg, ox, oy, *, keep_shape: bool = False):
            """Children at depth L-1 of nodes at depth L (yaw groups split, boxes split): ``ratio * 4``
            per node, in order; those outside the window are dropped (or, with ``keep_shape``,
            returned with ``valid`` False)."""
            g_hi, g_lo = self._yaw_group(L), self._yaw_group(L - 1)
            ratio = g_hi // g_lo
            hb = 1 << (L - 1)
            ys = (yg[:, None, None] * ratio + np.arange(ratio)[None, :, None]) + np.zeros(4, np.int64)
            xs = ox[:, None, None] + np.array([0, 0, hb, hb])[None, None, :] + np.zeros((1, ratio, 1), np.int64)
            zs = oy[:, None, None] + np.array([0, hb, 0, hb])[None, None, :] + np.zeros((1, ratio, 1), np.int64)
            ys, xs, zs = ys.reshape(len(yg), -1), xs.reshape(len(yg), -1), zs.reshape(len(yg), -1)
            valid = (xs <= self.w) & (zs <= self.w) & (ys * g_lo < self.n_yaw)
            if keep_shape:
                return np.where(valid, ys, 0), np.where(valid, xs, 0), np.where(valid, zs, 0), valid
            return ys[valid], xs[valid], zs[valid]

        def descend(L: int, yg, ox, oy) -> None:
            """Greedy, batched: from each given node, follow the best child down to a leaf."""
            nonlocal best, nodes
            y, x, z = yg, ox, oy
            for depth in range(L, 0, -1):
                y, x, z, valid = children(depth, y, x, z, keep_shape=True)
                s = score(depth - 1, y.ravel(), x.ravel(), z.ravel()).reshape(y.shape)
                nodes += s.size
                s = np.where(valid, s, -1)
                i = np.argmax(s, axis=1)
                r = np.arange(len(i))
                y, x, z, s = y[r, i], x[r, i], z[r, i], s[r, i]
            i = int(np.argmax(s))
            if s[i] > best[0]:
                best = (int(s[i]), int(y[i]), int(x[i]), int(z[i]))

        for L in range(top, -1, -1):
            order = np.argsort(-bound, kind="stable")
            if L == 0:
                i = order[0]
                if bound[i] > best[0]:
                    best = (int(bound[i]), int(yg[i]), int(ox[i]), int(oy[i]))
                break
            seeds = order[: p.seeds]
            descend(L, yg[seeds], ox[seeds], oy[seeds])
            keep = order[bound[order] > best[0]]
            if len(keep) > p.max_nodes:
                keep, exact = keep[: p.max_nodes], False
            if not len(keep):
                break
            yg, ox, oy = children(L, yg[keep], ox[keep], oy[keep])
            bound = score(L - 1, yg, ox, oy)
            nodes += len(bound)

        leaf, j, x, z = best
        if floor >= 0 and leaf == floor:  # no leaf above ``at_least`` (best starts there)
            return MatchResult(guess, 0.0, nodes, exact)
        out = np.eye(3)
        out[:2, :2] = _rot(np.array(yaws[j]))
        out[:2, 2] = self.center + t0 + res * np.array([x, z], dtype=np.float64)
        return MatchResult(out, leaf / (_Q * n_pts), nodes, exact)

    def evaluate(self, source: np.ndarray, pose: np.ndarray, *, prior: np.ndarray | None = None) -> float:
        """The score of one exact pose ``(3, 3)`` on the finest field (the objective of `match`,
        prior included), to compare poses refined off the grid, e.g. by ICP."""
        p, res = self.params, self.params.resolution
        src = np.asarray(source, dtype=np.float64)[:, :2]
        src = src[np.linalg.norm(src, axis=1) <= p.max_range]
        if len(src) < 3:
            return 0.0
        src = _subsample(src, 2 * res, p.max_points)
        if not hasattr(self, "grids"):  # the finest field only: the pooled grids wait for `match`
            self._build(int(np.ceil(np.linalg.norm(src, axis=1).max() / res)) + 1, pooled=False)
        pose = np.asarray(pose, dtype=np.float64)
        c = np.rint((src @ pose[:2, :2].T + pose[:2, 2] - self.center) / res).astype(np.int64) + self.half
        ok = ((c >= 0) & (c < self.size)).all(1)
        value = self.grids[0][c[ok, 0], c[ok, 1]].sum(dtype=np.int64) / (_Q * len(src))
        if prior is not None and p.prior_weight > 0:
            d = np.linalg.norm(pose[:2, 2] - np.asarray(prior, dtype=np.float64)[:2]) / p.prior_scale
            value -= p.prior_weight * d * d
        return float(value)

    def _grids_ready(self, src_cells: int) -> bool:
        return hasattr(self, "grids") and self.src_cells >= src_cells


def global_match(
    source: np.ndarray, target: np.ndarray, params: ScanMatchParams, guess: np.ndarray | None = None
) -> MatchResult:
    """`ScanMatcher` (target, params) `.match` (source, guess): one pair."""
    center = None if guess is None else np.asarray(guess, dtype=np.float64)[:2, 2]
    return ScanMatcher(target, params, center=center).match(source, guess)
