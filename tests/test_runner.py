"""The runner: one read of the input, the run's frames selected once, extra sinks opened once the
scene is known and closed when the method ends, the result files written (`strep_core.runner`)."""

from __future__ import annotations

import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from strep_core.config import RunConfig
from strep_core.errors import MethodError
from strep_core.events import ListSink
from strep_core.runner import load_input, run, run_input


class Recorder(ListSink):
    """A sink that is a context manager, as a recording is."""

    def __init__(self) -> None:
        super().__init__()
        self.entered = self.closed = False

    def __enter__(self) -> Recorder:
        self.entered = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.closed = True


def test_run_input_reads_once_and_opens_the_sinks_on_the_selected_scene(tmp_path: Path) -> None:
    config = RunConfig(method="icp", frames="2:40:3")
    reads: list[dict[str, Any]] = []
    scenes: list[Any] = []
    recorder, plain = Recorder(), ListSink()

    def read(options: dict[str, Any]) -> Any:
        reads.append(options)
        return load_input("sample:sim2d-small")

    def sinks(scene: Any) -> list[Any]:
        scenes.append(scene)
        return [recorder, plain]

    main = ListSink()
    result = run_input(read, config, out_dir=tmp_path / "out", sink=main, sinks=sinks)
    assert len(reads) == 1 and len(scenes) == 1
    np.testing.assert_array_equal(scenes[0].indices, np.arange(2, 40, 3))
    assert result.sequence is scenes[0] and result.config.frames == "2:40:3"
    assert recorder.entered and recorder.closed
    # the main sink sees the load and write stages; the extra sinks the run, start to result
    assert [e.stage for e in main.of_kind("stage")] == ["load", "write"]
    for extra in (recorder, plain):
        assert extra.events[0].kind == "start" and extra.events[-1].kind == "result"
        assert [e for e in main.events if e.kind not in ("stage",)] == [e for e in extra.events]
    # icp writes each pair's verdict and covariance too
    assert sorted(result.files) == ["config.json", "map.ply", "matches.json", "metrics.json", "trajectory.tum"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(result.files)


def test_the_same_run_from_a_path_and_from_memory() -> None:
    config = RunConfig(method="icp", frames="0:30")
    from_path = run_input("sample:sim2d-small", config)
    in_memory = run(load_input("sample:sim2d-small"), config)
    np.testing.assert_array_equal(from_path.poses, in_memory.poses)
    assert from_path.metrics["ate"] == in_memory.metrics["ate"] < 5.0


def test_a_failing_run_still_closes_the_sinks() -> None:
    recorder = Recorder()
    with pytest.raises(MethodError):
        run_input("sample:sim2d-small", RunConfig.model_construct(method="nope"), sinks=lambda scene: [recorder])
    assert recorder.entered and recorder.closed


_FAULTS = """
import resource
import numpy as np
from strep_core.config import RunConfig
from strep_core.runner import run_input
from strep_core.scanmatch import ScanMatcher, ScanMatchParams

rng = np.random.default_rng(0)
bearing = np.linspace(0, 2 * np.pi, 720, endpoint=False)
room = np.column_stack([np.cos(bearing), np.sin(bearing)]) * rng.uniform(4, 8, 720)[:, None]
params = ScanMatchParams(window=1.0, resolution=0.02, yaw_window=0.8)

def faults():  # minor page faults over five branch-and-bound searches, after one to warm up
    def search():
        ScanMatcher(room, params).match(room[::2] + 0.1, np.eye(3))
    search()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        search()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0

before = faults()
run_input("sample:sim2d-small", RunConfig(method="icp", frames="0:10"))
print(before, faults())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_a_run_keeps_freed_memory_for_the_next_search() -> None:
    """glibc maps large blocks afresh and hands the heap's top back, so each search's grids and
    score batches are faulted in again; a run tells it to keep freed memory
    (`strep_core.allocator`). In a fresh interpreter, five searches of a room fault in pages
    (about 14,000 here) before a run and (almost) none after it."""
    out = subprocess.run([sys.executable, "-c", _FAULTS], capture_output=True, text=True, check=True, timeout=300)
    before, after = (int(v) for v in out.stdout.split())
    if before == 0:
        pytest.skip("this allocator reuses freed blocks already")
    assert after <= before // 10, (before, after)
