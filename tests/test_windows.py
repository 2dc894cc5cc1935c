"""Learned runs from scratch past one batch: windows, their joins, the run end to end
(`strep_core.windows`, docs/design/long-scratch.md)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from strep_core import geometry as g
from strep_core import metrics
from strep_core.config import RunConfig
from strep_core.events import ListSink
from strep_core.methods import get
from strep_core.resolve import resolve
from strep_core.runner import run
from strep_core.sim.lidar2d import simulate_2d
from strep_core.windows import OVERLAP, join, join_on_map, windowed, windows


@pytest.mark.parametrize("frames", [257, 512, 1000, 2048])
def test_windows_cover_the_sequence_each_sharing_the_overlap(frames: int) -> None:
    wins = windows(frames, 256)
    assert all(len(w) == 256 and np.all(np.diff(w) == 1) for w in wins)
    assert wins[0][0] == 0 and wins[-1][-1] == frames - 1
    shared = [len(np.intersect1d(a, b)) for a, b in itertools.pairwise(wins)]
    assert min(shared) >= OVERLAP
    # linear cost: about one window per (256 - OVERLAP) frames, never all pairs
    assert len(wins) <= frames // (256 - OVERLAP) + 1


def test_join_moves_a_window_onto_the_frames_before_it() -> None:
    seq = simulate_2d(3, frames=40)
    gt = seq.poses
    done = np.zeros(40, bool)
    done[:30] = True
    window = np.arange(20, 40)
    # the window's own estimate: the truth in other axes (a rigid motion away)
    away = g.se2_from_xytheta(np.array([120.0, -40.0, 2.1]))
    est = away[None] @ gt[window]
    joined = join(gt, done, window, est, seq)
    np.testing.assert_allclose(joined, gt[window], atol=1e-6)
    # nothing shared: the window stays where it was
    np.testing.assert_allclose(join(gt, np.zeros(40, bool), window, est, seq), est)


def test_a_window_is_held_to_the_map_it_revisits_not_only_to_its_overlap() -> None:
    seq = simulate_2d(5, frames=60)
    gt = seq.poses
    done = np.zeros(60, bool)
    done[:30] = True
    window = np.arange(30, 60)  # shares no frame: the overlap fit has nothing to go on
    off = g.se2_from_xytheta(np.array([2.0, -1.5, np.radians(1.0)]))
    est = off[None] @ gt[window]
    np.testing.assert_allclose(join(gt, done, window, est, seq), est)
    placed = join_on_map(gt, done, window, est, seq)
    before = np.linalg.norm(est[:, :2, 2] - gt[window, :2, 2], axis=1).mean()
    after = np.linalg.norm(placed[:, :2, 2] - gt[window, :2, 2], axis=1).mean()
    assert before > 1.5 and after < 0.1 * before


def test_only_runs_from_scratch_longer_than_a_batch_go_by_windows() -> None:
    seq = simulate_2d(0, frames=300)
    scratch = resolve(RunConfig(method="strep", start="scratch"), seq).config
    warm = resolve(RunConfig(method="strep", init="identity", start="pose-graph"), seq).config
    assert scratch.optim.batch_frames == 256 and windowed(seq, scratch)
    assert not windowed(seq, warm)
    assert not windowed(
        seq.select("0:256"), resolve(RunConfig(method="strep", start="scratch"), seq.select("0:256")).config
    )


@pytest.mark.slow
@pytest.mark.accuracy
def test_a_windowed_run_registers_and_reports_as_one_run() -> None:
    seq = simulate_2d(0, frames=80)
    cfg = RunConfig.model_validate(
        {"method": "strep", "start": "scratch", "threads": 1, "optim": {"batch_frames": 32, "iterations": 40}}
    )
    sink = ListSink()
    res = run(seq, cfg, sink=sink)
    events = sink.of_kind("iteration")
    total = get("strep").total_iterations(seq, res.config)
    # one progress: iterations rise to the total across the windows and the refinement
    assert [e.total for e in events] == [total] * len(events)
    iters = [e.iteration for e in events]
    assert iters == sorted(iters) and iters[-1] == total == res.metrics["iterations"]
    assert all(len(e.poses) == 80 for e in events)
    assert res.metrics["windows"] == len(windows(80, 32)) == 4
    # registered: far below identity, and the refinement ends at or below the joined windows
    assert res.metrics["ate"] < 0.25 * metrics.ate(np.repeat(np.eye(3)[None], 80, 0), seq.poses)
    assert res.metrics["ate"] <= res.metrics["joined_ate"] * 1.05
