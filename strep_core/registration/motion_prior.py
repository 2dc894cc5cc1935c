"""Motion priors of the planar-laser local SLAM (`strep_core.registration.submaps`): score lost
by turning away from the motion, and by a straight step off a keyframed log's spacing. Poses
``(3, 3)`` SE(2); costs in score units (the share of a scan's likelihood, 0 to 1). Measurements:
docs/design/laser-slam.md, rounds 6-7."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from strep_core import geometry as g

STRAIGHT = float(np.radians(10.0))  # a step turning less than this is straight


def keyframe_spacing(moving: list[float] | np.ndarray) -> float | None:
    """The keyframe spacing of a log that keeps a scan per distance travelled: the median of its
    straight steps that moved (``moving``), where their 10th percentile lies within 25 % of the
    median, once 20 were seen; else None. Seven of the eight CARMEN logs do (5th percentile
    0.79-0.96 of the median), freiburg-079 does not (0.01 of 0.10 m; laser-slam.md, round 7)."""
    if len(moving) < 20:
        return None
    med = float(np.median(moving))
    return med if float(np.percentile(moving, 10)) >= 0.75 * med else None


def turn_cost(pred: np.ndarray, anchor: np.ndarray, pose: np.ndarray, weight: float) -> float:
    """Score lost by turning away from the motion: ``weight`` per radian squared from the
    nearer of two headings, the prediction's (the turn goes on) and the anchor's (it stopped)."""
    return weight * min(float(g.so2_angle(g.relative(a, pose)[:2, :2])) ** 2 for a in (pred, anchor))


def yaw_cost(pred: np.ndarray, anchor: np.ndarray, weight: float) -> Callable[[np.ndarray], np.ndarray]:
    """`turn_cost` as a function of the heading (radians, an array), for the branch and bound."""
    heads = [float(np.arctan2(a[1, 0], a[0, 0])) for a in (pred, anchor)]

    def cost(yaw: np.ndarray) -> np.ndarray:
        d = [np.angle(np.exp(1j * (yaw - h))) for h in heads]
        return weight * np.minimum(d[0] ** 2, d[1] ** 2)

    return cost


def keyframe_velocity(velocity: np.ndarray, spacing: float | None, travel: np.ndarray | None = None) -> np.ndarray:
    """``velocity``, its straight step (under 10 degrees) lengthened to the keyframe ``spacing``
    if shorter. Lengthening only: carried at the spacing both ways, freiburg-campus whole went
    0.42 -> 2.03 m (round 7). ``travel``: the unit direction (in the scan's frame) of the last
    long straight step; a short step pointing against it is noise about a slide, and is
    lengthened along ``travel`` instead (infinite-corridor scans 107-111 walked back 5 m along
    their own lengthened noise; docs/design/laser-slam.md, round 10)."""
    step = float(np.hypot(*velocity[:2, 2]))
    if (
        spacing is None
        or step < 1e-9
        or step >= spacing
        or abs(float(np.arctan2(velocity[1, 0], velocity[0, 0]))) >= STRAIGHT
    ):
        return velocity
    out = velocity.copy()
    if travel is not None and float(velocity[:2, 2] @ travel) < 0:
        out[:2, 2] = spacing * travel
        return out
    out[:2, 2] *= spacing / step
    return out


def keyframe_cost(anchor: np.ndarray, pose: np.ndarray, regular: float, weight: float) -> float:
    """Score lost by a straight step (under 10 degrees) off the keyframe spacing ``regular``:
    ``weight`` per the squared share it is off by; a turning step pays nothing."""
    rel = g.relative(anchor, pose)
    if abs(float(np.arctan2(rel[1, 0], rel[0, 0]))) >= STRAIGHT:
        return 0.0
    return weight * ((float(np.hypot(*rel[:2, 2])) - regular) / regular) ** 2
