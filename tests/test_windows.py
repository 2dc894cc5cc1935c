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
from strep_core.window_graph import chain, close_loops
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


def test_loops_across_windows_undo_a_window_bent_between_revisits() -> None:
    seq = simulate_2d(0, frames=640)  # revisits its start from about frame 200 on
    gt = seq.poses
    rng = np.random.default_rng(0)
    wins = windows(640, 256)
    ests = []
    for n, w in enumerate(wins):  # each window's own chain: the truth, noisy, the second bent
        bend = np.radians(0.03) if n == 1 else 0.0
        est = [np.eye(3)]
        for a, b in itertools.pairwise(w):
            noise = g.se2_from_xytheta(np.array([*rng.normal(0, 0.03, 2), bend + rng.normal(0, np.radians(0.03))]))
            est.append(est[-1] @ g.relative(gt[a], gt[b]) @ noise)
        ests.append(np.stack(est))
    joined = np.repeat(np.eye(3)[None], 640, 0)
    done = np.zeros(640, bool)
    for w, est in zip(wins, ests, strict=True):
        joined[w] = join_on_map(joined, done, w, est, seq)
        done[w] = True
    closed, report = close_loops(seq.frames, wins, ests, joined)
    before, after = metrics.ate(joined, gt), metrics.ate(closed, gt)
    assert before > 3.0  # the bend carried on by the joins (6.0 px here)
    assert after < 0.15 * before  # 0.22 px here
    assert 0 < report.inliers <= report.loops <= report.tried


def test_the_chain_takes_each_pair_from_the_window_where_it_is_most_central() -> None:
    gt = simulate_2d(1, frames=300).poses
    wins = windows(300, 256)
    assert len(wins) == 2 and wins[1][0] == 44  # 212 frames shared
    rng = np.random.default_rng(1)
    ests = [gt[w] @ g.se2_from_xytheta(rng.normal(0, 0.1, (len(w), 3))) for w in wins]  # two different guesses
    rels, spread = chain(wins, ests)
    assert len(rels) == 299

    def source(k: int) -> int:
        for n, (w, est) in enumerate(zip(wins, ests, strict=True)):
            a = k - int(w[0])
            if 0 <= a < len(w) - 1 and np.allclose(rels[k], g.relative(est[a], est[a + 1])):
                return n
        return -1

    # window 0 up to the middle of the shared frames, where it is as central as window 1, then window 1
    assert [source(k) for k in range(299)] == [0] * 150 + [1] * 149
    assert spread.shape == (3,) and np.all(spread > 0.05)  # the two windows disagree by about 0.1 a pair
