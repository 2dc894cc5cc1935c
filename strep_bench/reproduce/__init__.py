"""``strep reproduce``: test each claim of the STREP paper with the benchmark's own runs.

The paper (Wang, Shi, Li, Fang: "Unsupervised Learning of Global Registration of Temporal
Sequence of Point Clouds") makes five claims that this implementation can test:

1. On 2D sequences where DeepMapping fails (ATE above 100 px), STREP succeeds (about 10 px).
2. There is no sequence where DeepMapping succeeds and STREP fails.
3. On real indoor 3D depth, STREP's mean and best-case ATE and point L2 beat DeepMapping's
   (here: 7-Scenes windows and the simulated AVD-like set).
4. Linked latents beat unlinked latents (the ablation) on both metrics.
5. With the network, ``w`` and the occupancy MLP trained on some sequences and frozen,
   re-optimising only the latents registers unseen sequences at least as well as optimising
   from scratch, in less time.

`PLANS` lists the runs each mode makes (``quick``: a couple of minutes, for CI; ``full``: about
45 minutes on a quiet 2-core CPU). Every run is seeded; each finished run's row is
cached in ``<out>/rows-<mode>.json`` so an interrupted run resumes where it stopped. `main`
writes the report (markdown, one table and verdict per claim, PNG figures next to it and a
JSON of every row). Verdicts are computed from the numbers by the rules in `THRESHOLDS`,
stated in the report; nothing in the report is written by hand.

Modules: `plans` (which runs, their cost), `runs` (running and caching them), `stats`,
`claims` (tables and verdicts), `figures`, `report` (the markdown and `main`).
"""

from strep_bench.reproduce.claims import THRESHOLDS, VERDICTS, ClaimReport, claim1, claim2, claim3, claim4, claim5
from strep_bench.reproduce.plans import PLANS, Plan, RunSpec, build_runs, estimate
from strep_bench.reproduce.report import build_report, check_report, main, reproduce
from strep_bench.reproduce.runs import ReproduceError

__all__ = [
    "PLANS",
    "THRESHOLDS",
    "VERDICTS",
    "ClaimReport",
    "Plan",
    "ReproduceError",
    "RunSpec",
    "build_report",
    "build_runs",
    "check_report",
    "claim1",
    "claim2",
    "claim3",
    "claim4",
    "claim5",
    "estimate",
    "main",
    "reproduce",
]
