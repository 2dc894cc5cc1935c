"""Correlative scan matching of 2D scans: an exhaustive search over yaw and translation.

After Olson ("Real-time correlative scan matching", ICRA 2009): the target scan becomes a
likelihood field on a grid (``exp(-d^2 / 2 sigma^2)``, ``d`` the distance to its nearest
point, by `scipy.ndimage.distance_transform_edt`); every candidate pose of the source within
a window around the guess is scored by the mean field value under its transformed points,
and the best one wins. It needs no gradient and no basin: it finds a turn of 47 degrees and a
0.7 m offset from the guess where ICP, started from the guess or from yaw offsets, converges
to the wrong optimum (CARMEN intel[300:400], scans 356 to 357).

The search runs coarse to fine: the whole window at twice the resolution and yaw step, then
the neighbourhood of the best coarse pose at full resolution. Cost per pair: about
``(window / resolution)^2 * (yaw_window / yaw_step) * N`` field look-ups, N the source's points.

Conventions: 2D points ``(N, 2)`` in the sequence's unit; poses ``(3, 3)`` SE(2),
source -> target (``p_target = T p_source``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from strep_core import geometry as g


@dataclass(frozen=True)
class CorrelativeParams:
    """Window and grid of the search (lengths in the sequence's unit, angles in radians).

    Attributes:
        window: translations up to this far from the guess's, along each axis.
        yaw_window: yaw up to this far from the guess's.
        yaw_step: yaw step of the fine search (the coarse one takes twice this).
        resolution: grid cell of the fine search (the coarse one takes twice this).
        sigma: width of the likelihood field.
    """

    window: float
    yaw_window: float
    yaw_step: float
    resolution: float
    sigma: float


def likelihood_field(
    points: np.ndarray, resolution: float, margin: float, sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(field, origin)``: ``field[i, j]`` is the likelihood at ``origin + resolution * (i, j)``.

    The grid covers the points' bounding box plus ``margin`` on every side.
    """
    from scipy import ndimage

    lo = points.min(0) - margin
    shape = np.floor((points.max(0) + margin - lo) / resolution).astype(int) + 1
    free = np.ones(shape, dtype=bool)
    idx = np.floor((points - lo) / resolution).astype(int)
    free[idx[:, 0], idx[:, 1]] = False
    dist = ndimage.distance_transform_edt(free) * resolution
    return np.exp(-0.5 * (dist / sigma) ** 2), lo


def _search(
    source: np.ndarray,
    field: np.ndarray,
    origin: np.ndarray,
    resolution: float,
    guess_yaw: float,
    guess_t: np.ndarray,
    yaws: np.ndarray,
    shifts: np.ndarray,
) -> tuple[float, float, np.ndarray]:
    """Best ``(score, yaw, translation)`` over yaw offsets ``yaws`` and translation offsets
    ``shifts`` (grid steps along each axis) around ``(guess_yaw, guess_t)``."""
    best = (-1.0, guess_yaw, guess_t)
    ni, nj = field.shape
    for dyaw in yaws:
        yaw = guess_yaw + float(dyaw)
        p = source @ g.so2(np.float64(yaw)).T + guess_t
        cells = np.floor((p - origin) / resolution).astype(int)
        ii = cells[:, 0][None, :] + shifts[:, None]  # (S, N)
        jj = cells[:, 1][None, :] + shifts[:, None]
        inside = ((ii >= 0) & (ii < ni))[:, None, :] & ((jj >= 0) & (jj < nj))[None, :, :]
        vals = field[np.clip(ii, 0, ni - 1)[:, None, :], np.clip(jj, 0, nj - 1)[None, :, :]] * inside
        score = vals.mean(-1)  # (S, S): mean likelihood under every shifted copy
        a, b = np.unravel_index(int(np.argmax(score)), score.shape)
        if score[a, b] > best[0]:
            best = (float(score[a, b]), yaw, guess_t + resolution * np.array([shifts[a], shifts[b]], dtype=np.float64))
    return best


def correlative_match(
    source: np.ndarray, target: np.ndarray, guess: np.ndarray, params: CorrelativeParams
) -> tuple[np.ndarray, float]:
    """The best SE(2) source -> target pose within the window around ``guess``.

    Args:
        source, target: ``(N, 2)`` and ``(M, 2)`` points, each in its own frame.
        guess: ``(3, 3)`` initial source -> target transform.
        params: the window and grid.

    Returns:
        ``(T, score)``: the ``(3, 3)`` pose and its mean likelihood (0 to 1).
    """
    source = np.asarray(source, dtype=np.float64)[:, :2]
    target = np.asarray(target, dtype=np.float64)[:, :2]
    guess = np.asarray(guess, dtype=np.float64)
    yaw0 = float(g.so2_angle(guess[:2, :2]))
    t0 = guess[:2, 2].copy()
    margin = params.window + params.sigma * 3
    # coarse: the whole window at twice the cell and yaw step
    coarse = 2.0 * params.resolution
    field, origin = likelihood_field(target, coarse, margin, params.sigma)
    n = int(np.ceil(params.window / coarse))
    step = 2.0 * params.yaw_step
    m = int(np.ceil(params.yaw_window / step))
    _, yaw, t = _search(source, field, origin, coarse, yaw0, t0, step * np.arange(-m, m + 1), np.arange(-n, n + 1))
    # fine: one coarse step around the best coarse pose
    field, origin = likelihood_field(target, params.resolution, margin, params.sigma)
    yaws = params.yaw_step * np.arange(-2, 3)
    score, yaw, t = _search(source, field, origin, params.resolution, yaw, t, yaws, np.arange(-2, 3))
    out = np.eye(3)
    out[:2, :2] = g.so2(np.float64(yaw))
    out[:2, 2] = t
    return out, score
