"""``strep bench --executor ray``: the benchmark's runs spread over a Ray cluster.

Every (case, method) pair is one Ray task running `strep_bench.cases.run_case`; every node
needs strep-studio and the shared data at the same path (`docs/scaling.md`). Ray is imported
only here, and only when this runner is called.
"""

from __future__ import annotations

from typing import Any

from strep_bench.cases import BenchCase, run_case
from strep_core.errors import ConfigError, first_lines

RAY_MISSING = "--executor ray needs Ray, an optional extra: pip install 'strep-studio[ray]'"


def run_cases_ray(
    cases: list[BenchCase], methods: list[str], quick: bool, *, address: str = "local", cpus: int = 1
) -> list[dict[str, Any]]:
    """`run_case` for every (case, method) pair as one Ray task of ``cpus`` CPUs (and threads).

    Rows come back in the order of the sequential loop. Uses this process's Ray connection when
    there is one, else ``ray.init(address)`` (``local``: a new local runtime; ``auto``: the running
    cluster; or a cluster address) and shuts it down afterwards.
    """
    from tqdm import tqdm

    try:
        import ray
    except ImportError as exc:
        raise ConfigError(RAY_MISSING) from exc
    owns = not ray.is_initialized()
    if owns:
        ray.init(address=address, include_dashboard=False)
    try:
        task = ray.remote(num_cpus=cpus, max_retries=0)(run_case)
        pairs = [(case, m) for case in cases for m in methods]
        refs = [task.remote(case, [m], quick, threads=cpus) for case, m in pairs]
        pending = list(refs)
        with tqdm(total=len(refs), desc="bench (ray)", unit="run") as progress:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                progress.update(len(done))
        rows: list[dict[str, Any]] = []
        for (case, m), ref in zip(pairs, refs, strict=True):
            try:
                rows.extend(ray.get(ref))
            except ray.exceptions.RayError as exc:  # the task's worker died: a failed run, as in run_case
                rows.append({"method": m, "status": f"failed: {_ray_reason(exc)}", "ate": None, "point_l2": None})
                rows[-1].update({"suite": case.suite, "case": case.name, "unit": None})
        for row in rows:  # a failed task's unit: that of its case's other rows
            if row["unit"] is None:
                row["unit"] = next((r["unit"] for r in rows if r["case"] == row["case"] and r["unit"]), "?")
        return rows
    finally:
        if owns:
            ray.shutdown()


def _ray_reason(exc: BaseException) -> str:
    """One line for a failed Ray task: the cause's type and its useful line."""
    cause = getattr(exc, "cause", None) or exc
    return f"{type(cause).__name__}: {first_lines(str(cause))}"
