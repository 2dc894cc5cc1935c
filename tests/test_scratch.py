"""From scratch: the learned methods from identity with no classical step (the paper's setting)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from strep_core import losses
from strep_core.config import RunConfig
from strep_core.errors import ConfigError
from strep_core.events import ListSink
from strep_core.model import OccupancyMLP
from strep_core.neighbours import nearest_in_frame
from strep_core.profiles import START_OVERLAYS
from strep_core.resolve import resolve
from strep_core.runner import run
from strep_core.samples import load_sample

FRAMES = "0:32"
SCRATCH = START_OVERLAYS["scratch"]


def _scratch(method: str, iterations: int) -> RunConfig:
    return RunConfig.build(
        method=method, start="scratch", frames=FRAMES, threads=2, optim={"iterations": iterations, "event_interval": 25}
    )


@pytest.fixture(scope="module")
def strep_from_scratch():
    sink = ListSink()
    return run(load_sample("sim2d-small"), _scratch("strep", 300), sink=sink), sink


def test_strep_from_scratch_halves_the_ate_of_identity(strep_from_scratch) -> None:
    result, sink = strep_from_scratch
    assert result.initial_guess == "identity" and result.config.start == "scratch"
    assert result.metrics["initial_ate"] > 10  # px: 32 frames of a 2D walk, all at the origin
    assert result.metrics["ate"] < 0.5 * result.metrics["initial_ate"], result.metrics
    its = [e for e in sink.events if e.kind == "iteration"]
    assert its[0].iteration == 0 and its[0].ate == pytest.approx(result.metrics["initial_ate"], rel=1e-6)
    assert its[-1].iteration == 300 and its[-1].ate < its[0].ate


def test_scratch_profile_fills_only_what_is_left_out() -> None:
    seq = load_sample("sim2d-small").select(FRAMES)
    cfg = resolve(RunConfig.build(init="identity", loss={"robust": "truncated"}), seq).config
    assert cfg.start == "scratch"  # auto + identity
    assert cfg.loss.robust == "truncated"  # given
    assert cfg.loss.loop_radius_fraction == SCRATCH["loss"]["loop_radius_fraction"]  # left out
    assert cfg.model.link_init == SCRATCH["model"]["link_init"]
    again = RunConfig.model_validate_json(cfg.model_dump_json())
    assert resolve(again, seq).config == cfg  # a saved config reproduces its run
    warm = resolve(RunConfig.build(), seq).config
    assert (warm.start, warm.init, warm.optim.lr_latent) == ("pose-graph", "multiway", 1e-4)
    with pytest.raises(ConfigError, match="start 'scratch' runs no classical step"):
        RunConfig.build(start="scratch", init="icp")
    # the warm start's settings from identity (the benchmark's bunny[identity] rows), not scratch's
    plain = resolve(RunConfig.build(start="pose-graph", init="identity"), seq).config
    assert (plain.start, plain.init, plain.optim.lr_latent) == ("pose-graph", "identity", 1e-4)


def test_occupancy_labels_on_a_hand_made_scan() -> None:
    """A sensor at the origin sees a wall at x = 2: free-space samples lie strictly between the
    sensor and the wall, and an MLP trained on the labels says occupied at the wall and free in
    front of it."""
    torch.manual_seed(0)
    ys = torch.linspace(-1.5, 1.5, 64)
    hits = torch.stack([torch.full_like(ys, 2.0), ys], 1)
    origins = torch.zeros_like(hits)
    gen = torch.Generator().manual_seed(0)
    free = losses.free_space_samples(origins, hits, gen, per_ray=8)
    assert free[:, 0].min() >= 0.0 and free[:, 0].max() < 2.0  # labelled free: before the hit
    slope = free[:, 1] / free[:, 0].clamp_min(1e-9)  # on the ray to its own hit
    np.testing.assert_allclose(slope, hits[:, 1].repeat_interleave(8) / 2.0, atol=1e-4)
    mlp = OccupancyMLP(2, [32, 64, 32])
    opt = torch.optim.Adam(mlp.parameters(), lr=3e-3)
    values = []
    for _ in range(200):
        free = losses.free_space_samples(origins, hits, gen, per_ray=4)
        loss = losses.occupancy_bce(mlp(hits), mlp(free))
        opt.zero_grad()
        loss.backward()
        opt.step()
        values.append(loss.item())
    assert np.mean(values[-10:]) < 0.6 * values[0]
    with torch.no_grad():
        wall = torch.sigmoid(mlp(torch.tensor([[2.0, 0.0], [2.0, 1.0]])))
        front = torch.sigmoid(mlp(torch.tensor([[0.7, 0.0], [1.0, 0.3]])))
    assert (wall > 0.5).all() and (front < 0.5).all(), (wall, front)


# --------------------------------------------------------------------------------------------
# A depth camera turning in place (the simulated AVD-like walks)


def _pair_cost(a: np.ndarray, b: np.ndarray, rel: np.ndarray, robust: str) -> float:
    """Chamfer of frame ``b`` placed by ``rel`` against frame ``a`` (both directions), metres."""
    from strep_core import geometry as g

    pts = np.concatenate([a, g.apply(rel, b)])
    frame = np.r_[np.zeros(len(a), np.int64), np.ones(len(b), np.int64)]
    src = np.arange(len(pts))
    target = 1 - frame
    idx, _ = nearest_in_frame(pts, frame, src, target)
    cost = losses.chamfer_matches(
        torch.as_tensor(pts), src, idx, robust=robust, threshold=0.1, groups=frame * 2 + target, keep=0.5
    )
    return float(cost)


def test_trimmed_chamfer_puts_a_turn_where_huber_puts_half_of_it() -> None:
    """Why `SCRATCH_OVERLAYS["depth-turning"]` trims: two views 30 degrees apart share half their points."""
    from strep_core import geometry as g
    from strep_core.sim.depth3d import simulate_3d

    seq = simulate_3d(2000, frames=16)
    rng = np.random.default_rng(0)
    turns = 0
    for k in range(len(seq) - 1):
        rel = g.relative(seq.poses[k], seq.poses[k + 1])
        if g.rotation_angle(rel) < np.radians(20):
            continue  # a step, not a turn
        turns += 1
        a, b = (f[rng.choice(len(f), 800, replace=False)] for f in (seq.frames[k], seq.frames[k + 1]))
        half = g.se3_exp(0.5 * g.se3_log(rel))
        assert _pair_cost(a, b, rel, "trimmed") < _pair_cost(a, b, half, "trimmed"), k
        assert _pair_cost(a, b, half, "huber") < _pair_cost(a, b, rel, "huber"), k
    assert turns >= 3


def test_trimmed_mask_keeps_the_closest_fraction_of_each_group() -> None:
    d2 = np.array([5.0, 1.0, 3.0, 2.0, 9.0, 0.5, 7.0])
    groups = np.array([0, 0, 0, 0, 1, 1, 1])
    kept = losses.trimmed_mask(d2, groups, 0.5)
    assert kept.tolist() == [False, True, False, True, False, True, True]  # 2 of 4, then 2 of 3 (ceil)
    assert losses.trimmed_mask(d2, None, 0.01).sum() == 1  # at least one match counts


def test_a_turning_camera_from_scratch_gets_the_turning_overlay() -> None:
    from strep_core.profiles import SCRATCH_OVERLAYS
    from strep_core.sim.depth3d import simulate_3d

    seq = simulate_3d(2000, frames=16)
    cfg = resolve(RunConfig.build(method="strep", start="scratch"), seq).config
    assert cfg.profile == "depth-turning"
    assert (cfg.loss.robust, cfg.loss.window) == ("trimmed", 1)
    assert cfg.model.planar_axis == seq.meta["sensor"]["vertical_axis"]
    assert cfg.model.link_init == SCRATCH["model"]["link_init"]  # the scratch profile still under it
    given = resolve(RunConfig.build(method="strep", start="scratch", loss={"robust": "huber"}), seq).config
    assert (given.loss.robust, given.loss.window) == ("huber", 1)  # what the user gave wins
    warm = resolve(RunConfig.build(method="strep"), seq).config
    assert (warm.loss.robust, warm.model.planar_axis) == ("truncated", None)  # only from scratch
    assert resolve(RunConfig.model_validate(cfg.model_dump(mode="json")), seq).config == cfg  # config.json re-runs it
    flat = resolve(RunConfig.build(method="strep", start="scratch"), load_sample("sim2d-small")).config
    assert flat.loss.robust == SCRATCH["loss"]["robust"] and flat.model.planar_axis is None
    assert set(SCRATCH_OVERLAYS) <= {"depth-turning"}


def test_strep_from_scratch_registers_a_turning_camera_level() -> None:
    """A 16-frame walk of 30-degree turns and 0.3 m steps from identity: the corrections turn only
    about the camera's vertical axis, and the ATE falls well below identity's."""
    from strep_core.sim.depth3d import simulate_3d

    seq = simulate_3d(2001, frames=16)
    result = run(seq, RunConfig.build(method="strep", start="scratch", threads=2, optim={"iterations": 300}))
    up = np.asarray(seq.meta["sensor"]["vertical_axis"])
    rot, trans = result.poses[:, :3, :3], result.poses[:, :3, 3]
    np.testing.assert_allclose(rot @ up, np.tile(up, (len(seq), 1)), atol=1e-5)  # level: turned about "up"
    np.testing.assert_allclose(trans @ up, 0.0, atol=1e-5)  # moved across it
    assert result.metrics["ate"] < 0.7 * result.metrics["initial_ate"], result.metrics
    assert np.isfinite(result.poses).all()
