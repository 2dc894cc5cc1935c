"""Each pair of the ICP chain carries a verdict and a covariance; a step past the log's own motion
bound fails and is bridged at its guess (issue 32; docs/design/lidar.md, verdicts)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from strep_core import geometry as g
from strep_core.config import RunConfig
from strep_core.registration import chain
from strep_core.runner import run
from strep_core.sequence import Sequence


def _planes(rng: np.random.Generator, n: int, *, corridor: bool) -> np.ndarray:
    """Points on a 6 x 4 x 2.5 m room's floor, ceiling and walls; a corridor keeps only the floor,
    ceiling and the two long walls (nothing faces along x)."""
    faces = [(2, 0.0), (2, 2.5), (1, -2.0), (1, 2.0)] + ([] if corridor else [(0, -3.0), (0, 3.0)])
    out = []
    for axis, value in faces:
        p = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), rng.uniform(0, 2.5, n)])
        p[:, axis] = value
        out.append(p)
    return np.concatenate(out)


def _walk(corridor: bool, k: int = 14) -> Sequence:
    rng = np.random.default_rng(5)
    truth = np.stack([g.identity(3)] * k)
    for i in range(1, k):
        truth[i] = truth[i - 1] @ g.se3_from_vector(np.array([0.05, 0.02, 0.0, 0.0, 0.0, 0.01]))
    truth[:, :3, 3] += np.array([-1.0, 0.0, 1.2])
    frames = [g.apply(g.inverse(p), _planes(rng, 2500, corridor=corridor)) for p in truth]
    return Sequence(frames=frames, name="corridor" if corridor else "room", unit="m", poses=truth)


def test_each_pair_of_a_room_is_accepted_with_a_tight_covariance() -> None:
    result = run(_walk(corridor=False), RunConfig(method="icp", init="identity"))
    pairs = result.artifacts["matches"]["pairs"]
    assert [p["frame"] for p in pairs] == list(range(1, 14))
    assert {p["verdict"] for p in pairs} == {"accepted"}
    assert result.metrics["matches_failed"] == result.metrics["matches_ambiguous"] == 0
    for p in pairs:
        cov = np.array(p["covariance"])
        assert cov.shape == (6, 6)
        np.testing.assert_allclose(cov, cov.T, rtol=1e-6, atol=1e-14)
        assert np.linalg.eigvalsh(cov).min() > 0
        assert np.sqrt(np.diag(cov)[:3]).max() < 0.01  # metres
        assert p["step"] == pytest.approx(0.054, abs=0.01)
    assert result.metrics["ate"] < 0.01


def test_a_corridor_is_ambiguous_along_its_axis() -> None:
    result = run(_walk(corridor=True), RunConfig(method="icp", init="identity"))
    pairs = result.artifacts["matches"]["pairs"]
    assert {p["verdict"] for p in pairs} == {"ambiguous"}
    for p in pairs:
        sd = np.sqrt(np.diag(np.array(p["covariance"])))
        assert sd[0] > 5 * max(sd[1], sd[2])  # x, along the corridor, against y and z


def _jumpy(monkeypatch, *, from_the_guess_too: bool) -> None:
    """The eleventh pair's ICP lands 30 m away; ICP from the guess alone too, if asked."""
    icp_pair = chain.icp_pair
    state = {"pair": 0}

    def jumpy(source, target, init, params, **kw):
        res = icp_pair(source, target, init, params, **kw)
        retry = kw.get("yaw_search") is False  # `judge`'s second try, from the guess alone
        if not retry:
            state["pair"] += 1
        if state["pair"] == 11 and (from_the_guess_too or not retry):
            far = res.transformation.copy()
            far[:3, 3] += np.array([30.0, 0.0, 0.0])
            res = dataclasses.replace(res, transformation=far)
        return res

    monkeypatch.setattr(chain, "icp_pair", jumpy)


def test_a_step_past_the_bound_takes_its_guesss_basin(monkeypatch) -> None:
    _jumpy(monkeypatch, from_the_guess_too=False)
    result = run(_walk(corridor=False), RunConfig(method="icp", init="identity"))
    pairs = result.artifacts["matches"]["pairs"]
    assert [p["verdict"] for p in pairs].count("ambiguous") == 1 == result.metrics["matches_ambiguous"]
    assert pairs[10]["verdict"] == "ambiguous" and result.metrics["matches_failed"] == 0
    assert pairs[10]["step"] == pytest.approx(0.054, abs=0.01)  # ICP from the guess: the true step
    assert result.metrics["ate"] < 0.01


def test_a_step_past_the_bound_fails_and_is_bridged_at_its_guess(monkeypatch) -> None:
    _jumpy(monkeypatch, from_the_guess_too=True)
    result = run(_walk(corridor=False), RunConfig(method="icp", init="identity"))
    pairs = result.artifacts["matches"]["pairs"]
    assert [p["verdict"] for p in pairs].count("failed") == 1 == result.metrics["matches_failed"]
    bad = pairs[10]
    assert bad["frame"] == 11 and bad["verdict"] == "failed"
    assert bad["step"] == 0.0  # bridged at the guess: identity's relative motion
    assert np.sqrt(np.array(bad["covariance"])[0, 0]) > 1.0  # wide
    step = g.relative(result.poses[10], result.poses[11])
    assert np.linalg.norm(step[:3, 3]) < 1e-9
    assert result.metrics["ate"] < 0.1  # one missed 5.4 cm step, not a 30 m jump


def test_the_step_bound_comes_from_the_accepted_steps() -> None:
    bound = chain.StepBound(floor=0.5)
    assert bound.limit() == 1.0  # twice the floor until ten steps are known
    step = np.eye(4)
    for length in np.linspace(0.1, 1.0, 10):
        step[0, 3] = length
        bound.add(chain.PairResult(step.copy(), 1.0, 0.0))
    assert bound.limit() == pytest.approx(2 * np.percentile(np.linspace(0.1, 1.0, 10), 90))
    slow = chain.StepBound(floor=0.5)
    for _ in range(10):
        step[0, 3] = 0.01
        slow.add(chain.PairResult(step.copy(), 1.0, 0.0))
    assert slow.limit() == 0.5  # never below the floor
