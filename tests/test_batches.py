"""Batches of the learned refinement: the auto rule, the latent chain over a batch, and a real run in
small batches against the same run in one batch (docs/design/whole-logs.md)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from strep_core import geometry as g
from strep_core.batching import AUTO_BATCH_FRAMES, batch_schedule, batch_size, total_steps
from strep_core.config import RunConfig
from strep_core.events import ListSink
from strep_core.model import Latents
from strep_core.pairs import with_partners
from strep_core.runner import run
from strep_core.samples import load_sample
from strep_core.sequence import Sequence


def test_auto_keeps_one_batch_up_to_256_frames_and_bounded_batches_beyond() -> None:
    for k in (10, 100, 256):  # every benchmark window and sample: today's one batch of all frames
        assert batch_size(k, "auto") is None
        assert total_steps(k, RunConfig()) == RunConfig().optim.iterations
    for k in (257, 910, 5000):
        assert batch_size(k, "auto") == AUTO_BATCH_FRAMES
        batches = batch_schedule(k, AUTO_BATCH_FRAMES, 2)
        assert max(len(b) for b in batches) == AUTO_BATCH_FRAMES
        assert np.array_equal(np.unique(np.concatenate(batches)), np.arange(k))
        # each batch visited `iterations` times: every frame gets as many updates as in one batch
        assert total_steps(k, RunConfig()) == RunConfig().optim.iterations * len(batches)
    assert len(batch_schedule(910, 256, 2)) == 4
    assert batch_size(48, 12) == 12 and batch_size(48, 48) is None and batch_size(48, None) is None


def test_partners_outside_the_batch_are_marked_fixed() -> None:
    pairs = np.array([[1, 9], [9, 1], [2, 3], [5, 0]])
    frames, fixed = with_partners(np.arange(4), pairs)
    assert frames.tolist() == [0, 1, 2, 3, 9] and fixed.tolist() == [False, False, False, False, True]
    frames, fixed = with_partners(np.arange(4), np.zeros((0, 2), dtype=np.int64))
    assert frames.tolist() == [0, 1, 2, 3] and not fixed.any()


def test_the_latent_chain_over_a_batch_is_the_whole_sequences_chain() -> None:
    torch.manual_seed(0)
    lat = Latents(910, 16, linked=True, w_init=0.5)
    with torch.no_grad():
        lat.w.copy_(torch.linspace(-0.9, 0.9, 16))
    whole = lat()
    for upto in (1, 7, 256, 510, 910):
        assert torch.equal(lat(upto), whole[:upto])  # z_k from frame 0: the same numbers
    # the loop's step: the last batch's latents computed from frame 0 up to its end
    batch = batch_schedule(910, 256, 2)[1]
    assert torch.equal(lat(int(batch[-1]) + 1)[batch], whole[batch])
    # and by the recurrence z_k = z~_k + w z_{k-1} written out, in double precision
    raw, w = lat.raw.detach().double(), lat.w.detach().double()
    z = raw[0]
    for k in range(1, int(batch[-1]) + 1):
        z = raw[k] + w * z
    assert torch.allclose(lat(int(batch[-1]) + 1)[-1].double(), z, atol=1e-5)
    # gradient of the batch's loss reaches frames before the batch through w
    lat(int(batch[-1]) + 1)[batch].sum().backward()
    assert lat.raw.grad is not None and lat.raw.grad[: int(batch[0])].abs().sum() > 0


@pytest.fixture(scope="module")
def noisy40() -> Sequence:
    """The 2D sample's first 40 frames, 64 points each, ground truth with 3 px and 1 degree of noise
    per frame as the starting poses."""
    seq = load_sample("sim2d-small", frames="0:40")
    rng = np.random.default_rng(0)
    noise = np.c_[rng.normal(0, 3.0, (40, 2)), np.radians(rng.normal(0, 1.0, 40))]
    assert seq.poses is not None
    return replace(seq, frames=[f[::4] for f in seq.frames], initial_poses=seq.poses @ g.se2_from_xytheta(noise))


def _config(batch_frames: int | None) -> RunConfig:
    return RunConfig.model_validate(
        {
            "method": "strep",
            "init": "odometry",
            "threads": 1,
            "optim": {"iterations": 100, "batch_frames": batch_frames},
        }
    )


def test_small_batches_reach_the_ate_of_one_batch(noisy40: Sequence) -> None:
    whole = ListSink()
    one = run(noisy40, _config(None), sink=whole)
    sink = ListSink()
    small = run(noisy40, _config(12), sink=sink)
    # an event per event_interval sweeps of the 4 batches: as many as the one-batch run sends
    assert len(sink.of_kind("iteration")) == len(whole.of_kind("iteration"))
    batches = batch_schedule(40, 12, RunConfig().loss.window)
    assert len(batches) == 4
    assert small.iterations == 100 * len(batches)
    assert sink.of_kind("start")[0].total_iterations == small.iterations
    assert all(len(e.poses) == 40 for e in sink.of_kind("iteration"))
    start = one.metrics["initial_ate"]  # 4.10 px
    assert one.metrics["ate"] < 0.6 * start  # 2.00 px measured
    # 12-frame batches, each visited 100 times: about the ATE of every frame in every step. Seeds
    # 0, 1, 2 measured: one batch 2.00, 2.53, 2.62 px; 12-frame batches 2.56, 1.94, 2.44 px
    assert small.metrics["ate"] < 0.7 * start
    assert small.metrics["ate"] < 1.4 * one.metrics["ate"]
