"""The learned loop's parts: device choice, the frames' search index, the per-pair Chamfer term, the
batch plan and query samples, and the decoder's pooling (docs/design/optimiser.md)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from strep_core import geometry as g
from strep_core import losses
from strep_core.config import ModelConfig, RunConfig
from strep_core.device import resolve_device
from strep_core.errors import ConfigError
from strep_core.model import PoseDecoder
from strep_core.neighbours import PAD, FrameIndex, brute_nearest, nearest_in_frame
from strep_core.plan import build_plan, sample_slots


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_auto_device_is_cuda_only_when_torch_sees_one(monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    with pytest.raises(ConfigError):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda"
    assert RunConfig().device == "auto"


def _frames(sizes: list[int], dim: int, seed: int = 0) -> tuple[list[np.ndarray], torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    frames = [rng.normal(size=(n, dim)) for n in sizes]
    padded = np.full((len(sizes), max(sizes), dim), PAD)
    for k, f in enumerate(frames):
        padded[k, : len(f)] = f
    return frames, torch.tensor(padded, dtype=torch.float32), torch.tensor(sizes)


def test_the_kd_tree_finds_what_brute_force_finds() -> None:
    _, points, counts = _frames([40, 75, 12, 60], 3)
    rng = np.random.default_rng(1)
    targets = torch.tensor([1, 0, 3, 2, 1])
    queries = torch.tensor(rng.normal(size=(5, 9, 3)) * 1.5, dtype=torch.float32)
    queries[4] += 1e3  # far from every point: the lift must still keep it in its own frame
    tree = FrameIndex(points, counts, backend="tree")
    slot, found = tree.nearest(queries, targets)
    assert found.all()
    assert torch.equal(slot, brute_nearest(queries, points, targets))
    assert (slot < counts[targets][:, None]).all()
    # rows searched within a distance: found exactly where the nearest point is closer
    within = torch.tensor([True, False, True, True, False])
    near, ok = tree.nearest(queries, targets, within=within, limit=0.6)
    dist = (points[targets[:, None], slot] - queries).norm(dim=-1)
    assert torch.equal(ok, ~within[:, None] | (dist < 0.6))
    assert torch.equal(near[ok], slot[ok])


def _flat_reference(world, normals, frame, src, target, weights, robust, loop_robust, spatial, threshold):
    """The loop's Chamfer term as it was computed before the plan: flat matches in world axes."""
    idx, _ = nearest_in_frame(world.detach().numpy(), frame, src, target)
    groups = frame[src] * 100 + target
    total = world.sum() * 0.0
    for sel, kernel in ((~spatial, robust), (spatial, loop_robust)):
        if sel.any():
            cost = losses.chamfer_matches(
                world, src[sel], idx[sel], robust=kernel, threshold=threshold, normals=normals,
                weights=weights[sel], groups=groups[sel], keep=0.5,
            )  # fmt: skip
            total = total + cost * (sel.sum() / len(src))
    return total


@pytest.mark.parametrize(
    ("robust", "loop_robust"),
    [("truncated", "truncated"), ("huber", "truncated"), ("trimmed", "huber"), ("trimmed", "trimmed")],
)
def test_pair_chamfer_in_the_targets_axes_is_the_world_chamfer(robust: str, loop_robust: str) -> None:
    """Distances and point-to-plane residuals do not depend on the axes they are measured in."""
    frames, points, counts = _frames([30, 30, 30, 30, 30], 2, seed=3)
    k = len(frames)
    normals_local = torch.tensor(np.stack([losses.frame_normals(f) for f in frames]), dtype=torch.float32)
    xi = torch.tensor(np.c_[np.linspace(0, 0.4, k), np.linspace(0, -0.2, k), np.linspace(0, 0.3, k)]).float()
    xi.requires_grad_(True)
    poses = g.se2_from_xytheta(xi)
    pairs = np.array([(i, j) for i in range(k) for j in range(k) if i != j and (abs(i - j) <= 1 or abs(i - j) == 4)])
    spatial_pair = np.abs(pairs[:, 0] - pairs[:, 1]) > 1
    weight = np.where(spatial_pair, 0.25, 1.0)
    threshold = 0.3

    # flat layout: every point of the query frame against the target frame, in world axes
    world = torch.cat([g.apply(poses[f], points[f]) for f in range(k)])
    normals = torch.cat([normals_local[f] @ poses[f, :2, :2].T for f in range(k)])
    frame = np.repeat(np.arange(k), 30)
    src = np.concatenate([np.flatnonzero(frame == i) for i, _ in pairs])
    target = np.repeat(pairs[:, 1], 30)
    per_match = np.repeat(np.arange(len(pairs)), 30)
    expected = _flat_reference(
        world, normals, frame, src, target, weight[per_match], robust, loop_robust, spatial_pair[per_match], threshold
    )

    # per-pair layout: the query frame's points moved into the target frame's axes
    a, b = torch.tensor(pairs[:, 0]), torch.tensor(pairs[:, 1])
    rel = g.inverse(poses[b]) @ poses[a]
    moved = g.apply(rel, points[a])
    within = torch.tensor(spatial_pair) if loop_robust == "truncated" else None
    if robust == "truncated":
        within = torch.ones(len(pairs), dtype=torch.bool)
    slot, found = FrameIndex(points, counts).nearest(moved.detach(), b, within=within, limit=threshold)
    got = losses.pair_chamfer(
        moved, points[b[:, None], slot], normals_local[b[:, None], slot], torch.ones_like(slot, dtype=torch.bool),
        found, torch.tensor(spatial_pair), torch.tensor(weight, dtype=torch.float32),
        robust=robust, loop_robust=loop_robust, threshold=threshold,
    )  # fmt: skip
    assert float(got.detach()) == pytest.approx(float(expected.detach()), rel=1e-4)
    (grad_got,) = torch.autograd.grad(got, xi, retain_graph=True)  # the same pull on every pose
    (grad_expected,) = torch.autograd.grad(expected, xi)
    assert torch.allclose(grad_got, grad_expected, rtol=1e-3, atol=1e-5)


def test_plan_holds_temporal_and_spatial_pairs_and_fixed_partners() -> None:
    spatial = np.array([[1, 9], [9, 1], [0, 7], [7, 0]])
    plan = build_plan(np.arange(4), spatial, window=2, span_weight=True, device=torch.device("cpu"))
    assert plan.frames.tolist() == [0, 1, 2, 3, 7, 9] and plan.has_fixed and plan.upto == 4
    assert plan.moving_frames.tolist() == [0, 1, 2, 3]
    pairs = {(int(plan.frames[a]), int(plan.frames[b])) for a, b in zip(plan.src, plan.dst, strict=True)}
    temporal = {(i, j) for i in range(4) for j in range(4) if 0 < abs(i - j) <= 2}
    # 7 and 9 are within the window of each other but both fixed: no pair between them
    assert pairs == temporal | {(1, 9), (9, 1), (0, 7), (7, 0)}
    spans = (plan.frames[plan.src] - plan.frames[plan.dst]).abs()
    assert torch.equal(plan.spatial, spans > 2)
    assert torch.allclose(plan.weight, torch.clamp(2.0 / spans, max=1.0))


def test_query_samples_are_stratified() -> None:
    counts = torch.tensor([100, 5, 32, 33])
    gen = torch.Generator().manual_seed(0)
    slot, valid = sample_slots(counts, 32, 100, gen)
    assert slot.shape == (4, 32)
    assert valid.sum(1).tolist() == [32, 5, 32, 32]
    assert slot[1, :5].tolist() == [0, 1, 2, 3, 4] and slot[2].tolist() == list(range(32))  # all of a small frame
    for row, n in zip(slot, counts.tolist(), strict=True):  # sample j in stratum [j n / 32, (j + 1) n / 32]
        kept, j = row[: min(n, 32)], torch.arange(min(n, 32))
        assert (kept < n).all() and (kept.diff() >= 0).all()
        if n >= 32:
            assert (kept >= torch.floor(j * n / 32)).all() and (kept <= torch.floor((j + 1) * n / 32)).all()


@pytest.mark.parametrize("batch_norm", [False, True])
def test_decoder_pools_then_rectifies_as_the_paper_rectifies_then_pools(batch_norm: bool) -> None:
    """Channels first, pool before the last ReLU: the function of Linear + ReLU per point, then max."""
    torch.manual_seed(0)
    cfg = ModelConfig()
    dec = PoseDecoder(2, 16, cfg.point_layers, cfg.head_layers, batch_norm=batch_norm)
    torch.nn.init.normal_(dec.out.weight)
    pts, z = torch.randn(8, 16, 2), torch.randn(8, 16)
    got = dec(pts, z)
    h = torch.relu(dec.first_norm(dec.first_points(pts) + dec.first_latent(z)[:, None, :]))
    reference = dec.out(dec.head(dec.point_mlp(h).amax(dim=1)))  # ReLU on every point, then max
    assert torch.allclose(got, reference, atol=1e-5)


_READS = ("numpy", "item", "tolist", "__float__", "__int__", "__bool__")


def _brute_run(monkeypatch, seq, cfg, reads: list[int] | None = None):
    """A run with the GPU's search (brute force) on the CPU, counting host reads per iteration."""
    import strep_core.prepare as prepare_module
    from strep_core.events import NullSink
    from strep_core.methods.base import RunContext
    from strep_core.optimize import optimize

    monkeypatch.setattr(prepare_module, "FrameIndex", lambda p, c: FrameIndex(p, c, backend="brute"))
    if reads is not None:
        for name in _READS:
            fn = getattr(torch.Tensor, name)

            def counted(self, *a, _fn=fn, **k):
                if not sys._getframe(1).f_globals.get("__name__", "").startswith("torch.optim"):
                    reads[-1] += 1
                return _fn(self, *a, **k)

            monkeypatch.setattr(torch.Tensor, name, counted)

    class Ctx(RunContext):
        def check_cancel(self) -> None:  # once before every iteration
            if reads is not None:
                reads.append(0)

    init = np.broadcast_to(np.eye(3), (len(seq), 3, 3)).copy()
    return optimize(seq, init, cfg, Ctx(NullSink(), None, 0.0), variant="strep")


def test_the_gpus_search_reads_nothing_back_between_events(monkeypatch) -> None:
    """With brute-force search (a GPU's path) an iteration reads no tensor on the host, but for the
    loop pairs' refresh (every pair_interval iterations) and the events."""
    from strep_core.samples import load_sample

    seq = load_sample("sim2d-small", frames="0:24")
    from strep_core.resolve import resolve

    asked = RunConfig.build(method="strep", start="scratch", threads=1, optim={"iterations": 20, "event_interval": 8})
    cfg = resolve(asked, seq).config  # the start's overlay, as a run gets it
    reads = [0]
    _brute_run(monkeypatch, seq, cfg, reads)
    # reads[i + 1]: during iteration i (events after 8, 16 and 20 iterations; a refresh at 10)
    per_iteration = reads[1:]
    events, refreshes = {7, 15, 19}, {10}  # (19: the last event, the final pass and the model)
    assert all(r == 0 for i, r in enumerate(per_iteration) if i not in events | refreshes), per_iteration
    assert all(per_iteration[i] > 0 for i in events | refreshes)


def test_the_gpus_search_gives_the_kd_trees_poses(monkeypatch) -> None:
    from strep_core.events import NullSink
    from strep_core.methods.base import RunContext
    from strep_core.optimize import optimize
    from strep_core.samples import load_sample

    seq = load_sample("sim2d-small", frames="0:24")
    cfg = RunConfig.build(method="strep", start="scratch", threads=1, optim={"iterations": 30})
    init = np.broadcast_to(np.eye(3), (len(seq), 3, 3)).copy()
    tree = optimize(seq, init, cfg, RunContext(NullSink(), None, 0.0), variant="strep")
    brute = _brute_run(monkeypatch, seq, cfg)
    np.testing.assert_allclose(brute.poses, tree.poses, atol=1e-3 * seq.scale())
