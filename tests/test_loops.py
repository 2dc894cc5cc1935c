"""Loop closures verified by the global scan matcher: the heading gate (`loop_global_turn`,
docs/design/scan-matching.md, third part)."""

from __future__ import annotations

import numpy as np

from strep_core import geometry as g
from strep_core import registration as reg
from strep_core.config import ClassicalConfig
from strep_core.sequence import Sequence


def _room(rng: np.random.Generator, n: int = 500) -> np.ndarray:
    """World points on the walls of an irregular room (no symmetry), about 6 x 4 m."""
    corners = np.array([[-3.0, -2.0], [3.0, -2.0], [3.0, 0.5], [1.5, 0.5], [1.0, 2.2], [-3.0, 2.0]])
    seg = np.stack([corners, np.roll(corners, -1, 0)], 1)
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    pick = rng.choice(len(seg), n, p=lengths / lengths.sum())
    pts = seg[pick, 0] + rng.uniform(0, 1, n)[:, None] * (seg[pick, 1] - seg[pick, 0])
    return pts + rng.normal(0, 0.005, pts.shape)


def _closures(chain_turn_deg: float, max_turn_deg: float) -> tuple[list[reg.LoopClosure], np.ndarray]:
    """Two scans of one room, 0.3 m and 10 degrees apart; the chain's estimate of frame 1 is the
    truth turned by ``chain_turn_deg``. Returns the loop closures found and the true 1 -> 0 pose."""
    rng = np.random.default_rng(7)
    truth = g.se2_from_xytheta(np.array([[0.0, 0.0, 0.0], [0.3, 0.1, np.radians(10.0)]]))
    frames = [g.apply(g.inverse(p), _room(rng)) for p in truth]
    seq = Sequence(frames=frames, poses=truth)
    params = reg.resolve_params(seq, ClassicalConfig(scanmatch={"consecutive": "on"}))
    clouds = reg.prepare_frames(seq, params)
    chain = truth.copy()
    chain[1] = truth[1] @ g.se2_from_xytheta(np.array([[0.0, 0.0, np.radians(chain_turn_deg)]]))[0]
    found, tried = reg.global_loop_closures(
        clouds,
        chain,
        params,
        radius=10.0,
        min_gap=1,
        min_score=0.6,
        min_fitness=0.6,
        max_per_frame=1,
        max_turn=float(np.radians(max_turn_deg)),
    )
    assert tried == 1
    return found, g.relative(truth[0], truth[1])


def _yaw_and_shift(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    d = g.relative(a, b)
    return abs(float(np.degrees(g.so2_angle(g.rotation(d))))), float(np.linalg.norm(g.translation(d)))


def test_loop_that_agrees_with_the_chain_is_accepted() -> None:
    """The chain's heading is 20 degrees off: within the default 45, the loop enters and is right."""
    default = ClassicalConfig().posegraph.loop_global_turn
    found, truth = _closures(20.0, default)
    assert len(found) == 1
    yaw_err, t_err = _yaw_and_shift(truth, reg.from_se3(found[0].transformation[None], 2)[0])
    assert yaw_err < 1.0 and t_err < 0.05, (yaw_err, t_err)


def test_loop_that_turns_the_chain_by_a_half_turn_is_rejected() -> None:
    """The same scans with the chain's heading 180 degrees off: the matcher finds the same pose
    over every heading (accepted with the gate off), but it would turn the chain by a half turn,
    which a corridor's symmetry explains as well: the default gate rejects it."""
    found_off, truth = _closures(180.0, 180.0)
    assert len(found_off) == 1
    assert _yaw_and_shift(truth, reg.from_se3(found_off[0].transformation[None], 2)[0])[0] < 1.0
    found_on, _ = _closures(180.0, ClassicalConfig().posegraph.loop_global_turn)
    assert found_on == []
