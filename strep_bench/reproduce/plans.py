"""The runs each mode of ``strep reproduce`` makes (`PLANS`), and their cost model.

The cases are the benchmark's (`strep_bench.cases`): the same sequences, loaders and per-case
configs, with the plan's seeds, initial guesses and iteration counts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

from strep_bench.cases import SUITES, BenchCase
from strep_core.sequence import Sequence

LEARNED = ("deepmapping", "strep-nolink", "strep")
SETTINGS = {
    "warm": ("icp", "ICP warm start (`init=icp`)"),
    "cold": ("identity", "from scratch (`start=scratch`: identity, no classical step, the from-scratch settings)"),
}
TRANSFER_MODES = ("scratch", "frozen", "frozen-short")


@dataclass(frozen=True)
class Plan:
    """Which runs a mode makes. ``None`` iteration counts keep the benchmark's per-case counts
    (300, real 3D capped at `bench.REAL3D_ITERATIONS`)."""

    mode: str
    seeds_2d: tuple[int, ...]
    seeds_3d: tuple[int, ...]
    seeds_transfer: tuple[int, ...]
    v1_pose0_frames: int | None  # frames 0:N of v1_pose0; None: all 256; 0: left out
    sim2d_count: int  # the first N of the benchmark's sim2d trajectories
    sim2d_frames: int | None  # None: the benchmark's 256
    sevenscenes_windows: int  # the first N of the benchmark's 7-Scenes windows
    sim3d_count: int  # the first N of the benchmark's sim3d sequences
    iterations: int | None  # claims 1-4; None: the benchmark's
    transfer_train: int  # claim 5: training trajectories (map 0)
    transfer_test: int  # claim 5: unseen trajectories per test map (map 0 and map 1)
    transfer_frames: int
    transfer_iterations: int
    short_fraction: float = 1 / 3  # claim 5: frozen-short runs this fraction of the iterations


PLANS: dict[str, Plan] = {
    # about 45 minutes on a quiet 2-core CPU (see `estimate`), most of it the from-scratch 2D
    # runs (1000 iterations of 256 frames each): sized to fit a working session; each further
    # sim2d trajectory adds about 7 minutes, a second 3D seed about 11
    "full": Plan(
        mode="full",
        seeds_2d=(0,),
        seeds_3d=(0,),
        seeds_transfer=(0,),
        v1_pose0_frames=None,
        sim2d_count=3,
        sim2d_frames=None,
        sevenscenes_windows=3,
        sim3d_count=4,
        iterations=None,
        transfer_train=2,
        transfer_test=2,
        transfer_frames=256,
        transfer_iterations=300,
    ),
    # under a minute on a quiet 2-core CPU: short sequences, few iterations, two seeds
    "quick": Plan(
        mode="quick",
        seeds_2d=(0, 1),
        seeds_3d=(0, 1),
        seeds_transfer=(0,),
        v1_pose0_frames=48,
        sim2d_count=2,
        sim2d_frames=48,
        sevenscenes_windows=1,
        sim3d_count=1,
        iterations=20,
        transfer_train=1,
        transfer_test=1,
        transfer_frames=48,
        transfer_iterations=20,
    ),
    # the smallest plan that still fills every table (tests)
    "tiny": Plan(
        mode="tiny",
        seeds_2d=(0,),
        seeds_3d=(0,),
        seeds_transfer=(0,),
        v1_pose0_frames=0,
        sim2d_count=1,
        sim2d_frames=32,
        sevenscenes_windows=1,
        sim3d_count=0,
        iterations=10,
        transfer_train=1,
        transfer_test=1,
        transfer_frames=32,
        transfer_iterations=10,
    ),
}


@dataclass(frozen=True)
class Case:
    """A benchmark case with what the plan needs to know before loading it."""

    bench: BenchCase
    frames: int
    dim: int

    @property
    def name(self) -> str:
        return self.bench.name

    @property
    def suite(self) -> str:
        return self.bench.suite


def _first(it: Iterator[BenchCase], n: int) -> list[BenchCase]:
    return [c for _, c in zip(range(n), it, strict=False)]


def cases_2d(plan: Plan, data: Path) -> list[Case]:
    """v1_pose0 and the first sim2d trajectories of the benchmark (px)."""
    from strep_core.sim.lidar2d import simulate_2d

    out = []
    if plan.v1_pose0_frames != 0:
        (v1,) = _first(SUITES["v1_pose0"](data, False), 1)
        if plan.v1_pose0_frames is not None:
            n = plan.v1_pose0_frames

            def load_v1(load: Callable[[], Sequence] = v1.load, n: int = n) -> Sequence:
                seq = load().select(f"0:{n}")
                seq.name = f"v1_pose0[0:{n}]"
                return seq

            v1 = replace(v1, name=f"v1_pose0[0:{n}]", load=load_v1)
        out.append(Case(v1, plan.v1_pose0_frames or 256, 2))
    if plan.sim2d_frames is None:
        out += [Case(c, 256, 2) for c in _first(SUITES["sim2d"](data, False), plan.sim2d_count)]
    else:
        # the benchmark's trajectories (seed 1000 + i on map i % 3), shortened
        for i in range(plan.sim2d_count):
            m, f = i % 3, plan.sim2d_frames
            load = lambda i=i, m=m, f=f: simulate_2d(1000 + i, frames=f, map_seed=m)  # noqa: E731
            out.append(Case(BenchCase("sim2d", f"sim2d-m{m}-t{i}", load), f, 2))
    return out


def cases_3d(plan: Plan, data: Path) -> list[Case]:
    """The first 7-Scenes windows and sim3d sequences of the benchmark (16 frames, metres)."""
    out = [Case(c, 16, 3) for c in _first(SUITES["sevenscenes"](data, False), plan.sevenscenes_windows)]
    out += [Case(c, 16, 3) for c in _first(SUITES["sim3d"](data, False), plan.sim3d_count)]
    return out


def cases_transfer(plan: Plan) -> dict[str, list[Case]]:
    """Claim 5: training trajectories on map 0, unseen ones on map 0 and on map 1."""
    from strep_core.sim.lidar2d import simulate_2d

    f = plan.transfer_frames

    def make(role: str, base: int, m: int, n: int) -> list[Case]:
        return [
            Case(
                BenchCase(
                    f"transfer-{role}",
                    f"sim2d-s{base + j}-m{m}",
                    lambda s=base + j, m=m: simulate_2d(s, frames=f, map_seed=m),
                ),
                f,
                2,
            )
            for j in range(n)
        ]

    return {
        "train": make("train", 5000, 0, plan.transfer_train),
        "same-map": make("same-map", 5100, 0, plan.transfer_test),
        "other-map": make("other-map", 5200, 1, plan.transfer_test),
    }


@dataclass(frozen=True)
class RunSpec:
    """One run of the plan; `key` identifies its cached row."""

    claim: str  # "2d", "3d" or "transfer"
    case: Case = field(compare=False)
    method: str
    setting: str  # warm | cold | train | scratch | frozen | frozen-short
    init: str
    seed: int
    iterations: int | None  # None: the benchmark's
    model_in: str | None = None  # claim 5: model file to start from (relative to the out folder)
    model_out: str | None = None
    freeze: bool = False

    @property
    def key(self) -> str:
        it = "bench" if self.iterations is None else str(self.iterations)
        return (
            f"{self.claim}|{self.case.suite}|{self.case.name}|{self.case.frames}f|{self.method}|{self.setting}"
            f"|{self.init}|seed{self.seed}|{it}it"
        )

    def planned_iterations(self) -> int:
        from strep_core.config import OptimConfig
        from strep_core.profiles import START_OVERLAYS

        if self.setting == "cold":  # from scratch: the profile's count, not the case's warm-start cap
            n = int(START_OVERLAYS["scratch"]["optim"]["iterations"])
            return n if self.iterations is None else min(n, self.iterations)
        n = OptimConfig().iterations
        if self.case.bench.iterations is not None:
            n = min(n, self.case.bench.iterations)
        return n if self.iterations is None else min(n, self.iterations)


def build_runs(plan: Plan, data: Path) -> list[RunSpec]:
    """Every run of a plan, grouped by sequence (each sequence is loaded once)."""
    runs: list[RunSpec] = []
    # claims 1, 2 and 4 in 2D: the three learned methods warm and cold (from scratch)
    for case in cases_2d(plan, data):
        for setting, (init, _) in SETTINGS.items():
            for m in LEARNED:
                runs += [RunSpec("2d", case, m, setting, init, s, plan.iterations) for s in plan.seeds_2d]
    # claims 3 and 4: the three learned methods on real and simulated 3D depth, warm and cold
    for case in cases_3d(plan, data):
        for setting, (init, _) in SETTINGS.items():
            for m in LEARNED:
                runs += [RunSpec("3d", case, m, setting, init, s, plan.iterations) for s in plan.seeds_3d]
    # claim 5: per seed, train a chain over the training trajectories, then test frozen vs scratch
    tr = cases_transfer(plan)
    n, short = plan.transfer_iterations, max(1, round(plan.transfer_iterations * plan.short_fraction))
    for s in plan.seeds_transfer:
        prev = None
        for j, case in enumerate(tr["train"]):
            out = f"models/{plan.mode}-seed{s}-step{j}.pt"
            runs.append(RunSpec("transfer", case, "strep", "train", "icp", s, n, model_in=prev, model_out=out))
            prev = out
        for group in ("same-map", "other-map"):
            for case in tr[group]:
                runs.append(RunSpec("transfer", case, "strep", "scratch", "icp", s, n))
                runs.append(RunSpec("transfer", case, "strep", "frozen", "icp", s, n, model_in=prev, freeze=True))
                runs.append(
                    RunSpec("transfer", case, "strep", "frozen-short", "icp", s, short, model_in=prev, freeze=True)
                )
    return runs


_ITER_PER_FRAME = {2: 4.2e-4, 3: 1.5e-3}  # learned optimiser, per frame and iteration
_ICP_PER_FRAME = {2: 4e-3, 3: 0.1}  # the ICP warm start, per frame
_LOAD = {2: 0.3, 3: 1.0}  # loading or simulating a sequence
_OVERHEAD = 0.3  # per run: metrics, final pass


def estimate_run(spec: RunSpec) -> float:
    d, k = spec.case.dim, spec.case.frames
    it = spec.planned_iterations() * k * _ITER_PER_FRAME[d] * (0.8 if spec.freeze else 1.0)
    warm = _ICP_PER_FRAME[d] * k if spec.init == "icp" else 0.0
    return it + warm + _OVERHEAD


def estimate(runs: list[RunSpec]) -> dict[str, float]:
    """Estimated seconds per claim group and in total (loading each sequence once)."""
    out: dict[str, float] = {}
    seen: set[tuple[str, str]] = set()
    for r in runs:
        load = 0.0
        if (r.case.suite, r.case.name) not in seen:
            seen.add((r.case.suite, r.case.name))
            load = _LOAD[r.case.dim]
        out[r.claim] = out.get(r.claim, 0.0) + estimate_run(r) + load
    out["total"] = sum(out.values())
    return out
