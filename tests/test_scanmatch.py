"""The global 2D scan matcher (`strep_core.scanmatch`): any heading, a window of translations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from strep_core import geometry as g
from strep_core.scanmatch import ScanMatcher, ScanMatchParams, global_match


def _room(rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """Points on the walls of an irregular room (no symmetry), metres, about 6 x 4 m."""
    corners = np.array([[-3.0, -2.0], [3.0, -2.0], [3.0, 0.5], [1.5, 0.5], [1.0, 2.2], [-3.0, 2.0]])
    seg = np.stack([corners, np.roll(corners, -1, 0)], 1)
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    pick = rng.choice(len(seg), n, p=lengths / lengths.sum())
    u = rng.uniform(0, 1, n)[:, None]
    pts = seg[pick, 0] + u * (seg[pick, 1] - seg[pick, 0])
    box = np.array([[0.5, -1.0], [0.9, -1.0], [0.9, -0.6], [0.5, -0.6]])  # a pillar
    pts = np.concatenate([pts, box[rng.integers(0, 4, 60)] + rng.normal(0, 0.01, (60, 2))])
    return pts + rng.normal(0, 0.01, pts.shape)


def _errors(truth: np.ndarray, found: np.ndarray) -> tuple[float, float]:
    err = g.relative(truth, found)
    return abs(float(np.degrees(g.so2_angle(g.rotation(err))))), float(np.linalg.norm(g.translation(err)))


PARAMS = ScanMatchParams(window=1.5, resolution=0.05, max_range=10.0)


@pytest.mark.parametrize("turn", [90.0, 135.0, 180.0, -135.0])
def test_global_match_recovers_a_synthetic_pair_turned_by(turn: float) -> None:
    rng = np.random.default_rng(int(abs(turn)))
    target = _room(rng)
    truth = g.se2_from_xytheta(np.array([[0.6, -0.4, np.radians(turn)]]))[0]
    source = g.apply(g.inverse(truth), _room(rng))  # a second scan of the same room, moved
    found = global_match(source, target, PARAMS)
    yaw_err, t_err = _errors(truth, found.pose)
    assert yaw_err <= 1.0 and t_err <= 0.08, (yaw_err, t_err)
    assert found.score > 0.8 and found.exact
    # the matcher's own score of the truth is no better than what it found (it is the optimum)
    matcher = ScanMatcher(target, PARAMS)
    assert matcher.evaluate(source, truth) <= found.score + 0.05


def test_global_match_prior_breaks_a_corridor_tie() -> None:
    """A straight corridor of two walls looks the same after any slide along it: with a prior on
    the step, the matcher takes the slide nearest the prior."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-6, 6, 400)
    walls = np.stack([x, np.where(rng.uniform(size=400) < 0.5, -1.0, 1.0)], 1)
    truth = g.se2_from_xytheta(np.array([[0.9, 0.0, 0.0]]))[0]
    source = g.apply(g.inverse(truth), walls[np.abs(walls[:, 0]) < 4.5])
    params = dataclasses.replace(PARAMS, prior_weight=0.2, prior_scale=2.0)
    found = ScanMatcher(walls, params).match(source, prior=np.array([1.0, 0.0]))
    assert _errors(truth, found.pose)[1] <= 0.15


def test_the_runner_up_lies_outside_the_excluded_disc() -> None:
    """A corridor with a doorpost every metre matches itself one post on about as well: with the
    best peak's disc left out, the runner-up is that alias, outside the disc and nearly as high.
    In an irregular room the runner-up scores clearly lower (one peak)."""
    rng = np.random.default_rng(4)
    x = rng.uniform(-9, 9, 600)
    walls = np.stack([x, np.where(rng.uniform(size=600) < 0.5, -1.0, 1.0)], 1)
    posts = np.stack([np.repeat(np.arange(-9.0, 10.0), 8), np.tile(np.linspace(0.6, 1.0, 8), 19)], 1)
    corridor = np.concatenate([walls, posts, posts * [1, -1]])
    truth = g.se2_from_xytheta(np.array([[0.3, 0.0, 0.0]]))[0]
    source = g.apply(g.inverse(truth), corridor[np.abs(corridor[:, 0]) < 4.0])
    matcher = ScanMatcher(corridor, dataclasses.replace(PARAMS, window=1.5, yaw_window=0.2))
    best = matcher.match(source)
    second = matcher.match(source, exclude=(best.pose[:2, 2], 0.4))
    gap = np.hypot(*(second.pose[:2, 2] - best.pose[:2, 2]))
    assert 0.8 < gap < 1.2, gap  # the next post
    assert best.score - 0.1 <= second.score <= best.score
    target = _room(rng)
    truth = g.se2_from_xytheta(np.array([[0.3, -0.2, 0.4]]))[0]
    source = g.apply(g.inverse(truth), _room(rng))
    matcher = ScanMatcher(target, PARAMS)
    best = matcher.match(source)
    assert _errors(truth, best.pose)[1] <= 0.08
    second = matcher.match(source, exclude=(best.pose[:2, 2], 0.4))
    assert np.hypot(*(second.pose[:2, 2] - best.pose[:2, 2])) > 0.4
    assert second.score < best.score - 0.2


def test_a_search_with_a_floor_finds_the_same_peak_or_none() -> None:
    """`at_least` below the best score: the same pose and score, with fewer nodes scored. Above
    it: nothing (score 0, the guess back). A room matched against another room scores below half
    the true pair's, and a floor there prunes most of the search."""
    rng = np.random.default_rng(5)
    target = _room(rng)
    truth = g.se2_from_xytheta(np.array([[0.5, 0.3, np.radians(120.0)]]))[0]
    source = g.apply(g.inverse(truth), _room(rng))
    plain = ScanMatcher(target, PARAMS).match(source)
    floored = ScanMatcher(target, PARAMS).match(source, at_least=0.8 * plain.score)
    assert np.array_equal(floored.pose, plain.pose) and floored.score == plain.score
    assert floored.nodes < plain.nodes
    guess = g.se2_from_xytheta(np.array([[0.2, 0.1, 0.0]]))[0]
    none = ScanMatcher(target, PARAMS).match(source, guess, at_least=plain.score + 0.01)
    assert none.score == 0.0 and np.array_equal(none.pose, guess)
    other = g.apply(g.se2_from_xytheta(np.array([[0.0, 0.0, 0.7]]))[0], rng.uniform(-3, 3, (300, 2)))
    wrong = ScanMatcher(target, PARAMS).match(other)
    assert wrong.score < 0.5 * plain.score
    pruned = ScanMatcher(target, PARAMS).match(other, at_least=0.8 * plain.score)
    assert pruned.score == 0.0 and pruned.nodes < 0.5 * wrong.nodes, (pruned.nodes, wrong.nodes)


def test_a_heading_cost_picks_among_equal_headings() -> None:
    """A square room scores the same at every quarter turn; the heading cost of the branch and
    bound (score lost per heading) decides, and the search stays exact."""
    side = np.linspace(-2.0, 2.0, 60)
    room = np.concatenate([np.stack([side, np.full(60, c)], 1) for c in (-2.0, 2.0)])
    room = np.concatenate([room, room[:, ::-1]])
    for want in (0.0, np.pi / 2, -np.pi / 2):
        cost = lambda yaw, want=want: 0.2 * np.angle(np.exp(1j * (yaw - want))) ** 2  # noqa: E731
        found = ScanMatcher(room, dataclasses.replace(PARAMS, window=0.5)).match(room, yaw_cost=cost)
        assert abs(np.angle(np.exp(1j * (np.arctan2(found.pose[1, 0], found.pose[0, 0]) - want)))) < np.radians(1.5)
        assert np.hypot(*found.pose[:2, 2]) < 0.1
        assert found.exact


def test_global_match_recovers_a_real_belgioioso_turn(shared_data) -> None:
    """belgioioso keyframe pairs turning by 81, 49 and 51 degrees, from identity. (Of the log's seven
    turns over 45 degrees, six match scan to scan; 125 -> 126 matches 90 degrees off.)"""
    from strep_core.io.carmen import read_carmen

    seq = read_carmen(shared_data / "carmen" / "belgioioso-corrected.log.gz")
    s = seq.scale()
    params = ScanMatchParams(window=1.5 * s, resolution=0.025 * s, max_range=8 * s)
    for a, b in [(109, 110), (100, 101), (30, 31)]:
        truth = g.relative(seq.poses[a], seq.poses[b])
        assert abs(np.degrees(g.so2_angle(g.rotation(truth)))) > 45
        found = global_match(seq.frames[b], seq.frames[a], params)
        yaw_err, t_err = _errors(truth, found.pose)
        # on the grid (7.8 cm cells here, 1 degree): within a degree and two cells; ICP refines it
        assert yaw_err <= 1.5 and t_err <= 2 * params.resolution, (a, b, yaw_err, t_err)


def test_icp_uses_the_global_match_on_2d_data_only(shared_data) -> None:
    """The default front end of 2D sequences: ICP from identity recovers an 81-degree keyframe
    turn through the global match, and the matcher is off in 3D."""
    from strep_core import registration as reg
    from strep_core.config import ClassicalConfig
    from strep_core.io.carmen import read_carmen

    seq = read_carmen(shared_data / "carmen" / "belgioioso-corrected.log.gz", frames="109:111")
    params = reg.resolve_params(seq, ClassicalConfig())
    assert params.global_match is not None
    found, _ = reg.align_frames(seq.frames[1], seq.frames[0], None, params)
    truth = g.relative(seq.poses[0], seq.poses[1])
    yaw_err, t_err = _errors(truth, found)
    assert yaw_err <= 1.0 and t_err <= 0.05, (yaw_err, t_err)
    off = reg.resolve_params(seq, ClassicalConfig(scanmatch={"consecutive": "off"}))
    assert off.global_match is None


def test_each_depth_pools_the_field_over_its_widened_box() -> None:
    """Every pooled grid is, cell by cell, the max of the finest field over the node's box
    widened by the depth's dilation (``[-dil, 2^L - 1 + dil]`` on both axes): the bound the
    branch and bound relies on, here checked by brute force on a small room; each depth is
    computed from the one before, so an error at one depth would carry to all that follow."""
    rng = np.random.default_rng(7)
    params = dataclasses.replace(PARAMS, window=0.8, resolution=0.1, max_range=4.0)
    matcher = ScanMatcher(_room(rng, 150), params)
    matcher.match(_room(rng, 150))
    field = matcher.grids[0].astype(np.int64)
    assert matcher.depth >= 3 and max(matcher.dil) > 0  # the dilated depths are exercised
    n = field.shape[0]
    for L in range(1, matcher.depth + 1):
        lo, hi = -matcher.dil[L], (1 << L) - 1 + matcher.dil[L]
        padded = np.pad(field, ((-lo, hi), (-lo, hi)))
        want = np.zeros_like(field)
        for dx in range(hi - lo + 1):
            for dy in range(hi - lo + 1):
                want = np.maximum(want, padded[dx : dx + n, dy : dy + n])
        assert np.array_equal(matcher.grids[L], want), L
    assert (matcher.grids[matcher.depth] >= field).all() and matcher.grids[matcher.depth].max() == field.max()
