"""The global match's step prior after turns in place (`scanmatch.prior_stop`,
docs/design/scan-matching.md, fourth part)."""

from __future__ import annotations

import numpy as np

from strep_core import geometry as g
from strep_core import registration as reg
from strep_core.config import ClassicalConfig
from strep_core.profiles import overlay
from strep_core.sequence import Sequence


def _step(x: float, yaw_deg: float) -> reg.PairResult:
    return reg.PairResult(
        transformation=g.to_se3(g.se2_from_xytheta(np.array([[x, 0.0, np.radians(yaw_deg)]])))[0],
        fitness=1.0,
        inlier_rmse=0.0,
    )


# two steps of 1 m, then three keyframes turned in place (a few cm, 30 degrees each)
AFTER_TURNS = [_step(1.0, 2.0), _step(0.96, -1.0), _step(0.02, 30.0), _step(0.03, 31.0), _step(0.01, 29.0)]


def test_step_prior_after_turns_in_place_is_the_moving_step() -> None:
    old = reg.step_prior(AFTER_TURNS)
    new = reg.step_prior(AFTER_TURNS, stop=0.25)
    assert old is not None and new is not None
    assert abs(old[0, 3] - 0.03) < 1e-9  # the median of the last 5: a stop
    assert abs(new[0, 3] - 0.98) < 1e-9  # the median of the last longer steps
    assert np.allclose(new[:3, :3], np.eye(3))  # no turn
    # a median that is not a stop stays as it was
    moving = [_step(1.0, 0.0), _step(0.9, 0.0), _step(0.02, 30.0), _step(1.1, 0.0), _step(1.05, 0.0)]
    assert np.allclose(reg.step_prior(moving, stop=0.25), reg.step_prior(moving))
    # only stops so far: nothing to take instead
    stops = AFTER_TURNS[2:]
    assert np.allclose(reg.step_prior(stops, stop=0.25), reg.step_prior(stops))


def test_corridor_pair_after_turns_in_place_keeps_the_step() -> None:
    """Two scans of a featureless corridor 1 m apart (the target's walls longer than the source's:
    every slide overlaps as well), the guess a stop (the last pair turned in place): only the
    prior tells the slide. With the default the pair keeps its 1 m step; with the prior of the
    last 5 steps (a stop) it slides back to no motion."""
    rng = np.random.default_rng(5)

    def walls(x0: float, x1: float, n: int) -> np.ndarray:
        x = rng.uniform(x0, x1, n)
        return np.stack([x, np.where(rng.uniform(size=n) < 0.5, -1.2, 1.2)], 1) + rng.normal(0, 0.01, (n, 2))

    truth = g.se2_from_xytheta(np.array([[1.0, 0.0, 0.0]]))[0]
    target = walls(-10.0, 10.0, 800)
    source = g.apply(g.inverse(truth), walls(-2.0, 4.0, 300))
    seq = Sequence(frames=[target, source], poses=np.stack([np.eye(3), truth]))
    cfg = ClassicalConfig(**overlay("laser-keyframes")["classical"])
    params = reg.resolve_params(seq, cfg)
    stop = cfg.scanmatch.prior_stop * seq.scale()
    assert 0.03 < stop < 0.96  # the turns in place are stops, the 1 m steps are not
    clouds = reg.prepare_frames(seq, params)
    steps = {}
    for name, s in (("default", stop), ("off", 0.0)):
        prior = reg.step_prior(AFTER_TURNS, stop=s)
        res = reg.icp_pair(clouds[1], clouds[0], np.eye(4), params, prior=prior)
        steps[name] = float(res.transformation[0, 3])
        assert abs(res.transformation[1, 3]) < 0.05  # across the corridor: the walls fix it
    assert abs(steps["default"] - 1.0) < 0.15, steps
    assert steps["off"] < 0.3, steps  # the old prior (a stop): slid back to no motion or beyond
