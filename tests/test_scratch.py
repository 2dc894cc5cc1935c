"""From scratch: the learned methods from identity with no classical step (the paper's setting)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from strep_core import losses
from strep_core.config import SCRATCH_PROFILE, RunConfig
from strep_core.errors import ConfigError
from strep_core.events import ListSink
from strep_core.model import OccupancyMLP
from strep_core.runner import run
from strep_core.samples import load_sample

FRAMES = "0:32"


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
    cfg = RunConfig.build(init="identity", loss={"robust": "truncated"})
    assert cfg.start == "scratch"  # auto + identity
    assert cfg.loss.robust == "truncated"  # given
    assert cfg.loss.loop_radius == SCRATCH_PROFILE["loss"]["loop_radius"]  # left out
    assert cfg.model.link_init == SCRATCH_PROFILE["model"]["link_init"]
    again = RunConfig.model_validate_json(cfg.model_dump_json())
    assert again == cfg  # a saved config reproduces its run
    warm = RunConfig.build()
    assert (warm.start, warm.init, warm.optim.lr_latent) == ("pose-graph", "auto", 1e-4)
    with pytest.raises(ConfigError, match="start 'scratch' runs no classical step"):
        RunConfig.build(start="scratch", init="icp")
    with pytest.raises(ConfigError, match="start 'pose-graph'"):
        RunConfig.build(start="pose-graph", init="identity")


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
