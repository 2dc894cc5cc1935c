"""`strep reproduce`: the report is produced from real runs, complete, and resumable.

The end-to-end test runs the smallest plan (``PLANS["tiny"]``: every claim's table filled,
seconds of compute); it checks the report's shape and provenance, never which verdicts come out.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from PIL import Image

from strep_bench.reproduce import PLANS, VERDICTS, build_runs, claim1, claim2, estimate, reproduce
from strep_cli import make_parser

NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e[+-]?\d+)?")


def _sections(text: str) -> dict[int, str]:
    parts = re.split(r"^## ", text, flags=re.M)
    return {int(m.group(1)): p for p in parts if (m := re.match(r"Claim (\d):", p))}


def _table_cells(section: str) -> list[list[str]]:
    """Data rows of every markdown table in a section (header and separator rows dropped)."""
    rows, in_table = [], False
    for line in section.splitlines():
        if not line.startswith("|"):
            in_table = False
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not in_table:  # the header
            in_table = True
            continue
        if not line.startswith("|---"):
            rows.append(cells)
    return rows


def _numeric(cell: str) -> float | None:
    """The leading number of a cell such as ``0.845 ± 0.01``, ``5.03 mm`` or ``1.2 (1/1 ok, ...)``."""
    m = NUMBER.match(cell.strip("*"))
    return float(m.group(0)) if m else None


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_reproduce_writes_a_complete_report_from_real_runs(tmp_path: Path, shared_data: Path) -> None:
    plan = PLANS["tiny"]
    docs = tmp_path / "docs" / "reproduction.md"
    out = tmp_path / "cache"
    report = reproduce(plan, out=out, docs=docs, data=shared_data, progress=False)
    assert report["problems"] == []
    runs = build_runs(plan, shared_data)
    assert report["ran"] == len(runs)

    text = docs.read_text()
    sections = _sections(text)
    assert sorted(sections) == [1, 2, 3, 4, 5]
    for n, sec in sections.items():
        verdict = re.search(r"\*\*Verdict: ([a-z ]+)\.\*\* \S", sec)
        assert verdict and verdict.group(1) in VERDICTS, n
        rows = _table_cells(sec)
        assert rows, f"claim {n}: no table"
        values = [v for r in rows for c in r[1:] if (v := _numeric(c)) is not None]
        # counts alone (claim 2) are numbers too; every claim has some non-trivial number
        assert values and any(v != 0 for v in values), f"claim {n}: no numbers in {rows}"
    # the measured ATE cells are positive numbers: claim 1 per sequence (DeepMapping, STREP), claims 3, 4, 5
    per_seq = [r for r in _table_cells(sections[1]) if "ok," in r[3]]
    assert per_seq and all(_numeric(r[3]) > 0 and _numeric(r[5]) > 0 for r in per_seq)
    for n, col in ((3, 4), (4, 3), (5, 4)):
        cells = [r[col] for r in _table_cells(sections[n]) if len(r) > col and _numeric(r[col]) is not None]
        assert cells and all(_numeric(c) > 0 for c in cells), (n, cells)
    assert "CPU cores" in text and "Wall time" in text

    # figures: referenced, present, valid PNGs
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", text)
    assert len(figures) == 4
    for rel in figures:
        path = docs.parent / rel
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", rel
        with Image.open(path) as im:
            im.verify()
            assert im.size[0] > 300 and im.size[1] > 200

    # every row comes from a finished run
    data = json.loads((docs.parent / "reproduction" / "reproduction.json").read_text())
    assert len(data["rows"]) == len(runs)
    assert {r["key"] for r in data["rows"]} == {r.key for r in runs}
    for r in data["rows"]:
        assert r["status"] == "ok", r["key"]
        assert r["wall_seconds"] > 0 and r["run_seconds"] > 0
        assert r["iterations"] >= 1 and r["history"], r["key"]
        assert r["ate"] is not None and r["ate"] >= 0
    assert set(data["verdicts"]) == {"1", "2", "3", "4", "5"}
    assert all(v["verdict"] in VERDICTS for v in data["verdicts"].values())

    # a second invocation resumes from the cache: nothing runs again, the same verdicts
    again = reproduce(plan, out=out, docs=docs, data=shared_data, progress=False)
    assert again["ran"] == 0
    assert again["verdicts"] == report["verdicts"]


def _row(case: str, method: str, ate: float, seed: int = 0, setting: str = "cold") -> dict:
    return {
        "key": f"{case}|{method}|{seed}|{setting}",
        "claim": "2d",
        "suite": "sim2d",
        "case": case,
        "method": method,
        "setting": setting,
        "seed": seed,
        "unit": "px",
        "status": "ok",
        "ate": ate,
        "initial_ate": 150.0,
    }


def test_claims_1_and_2_follow_their_thresholds() -> None:
    # DeepMapping fails on a, STREP rescues it; both succeed on b
    rows = [
        _row("a", "deepmapping", 150.0),
        _row("a", "strep", 8.0),
        _row("b", "deepmapping", 5.0),
        _row("b", "strep", 6.0),
    ]
    assert claim1(rows).verdict == "holds"
    assert claim2(rows).verdict == "holds"
    # STREP fails where DeepMapping fails too, and fails where DeepMapping succeeds
    rows = [
        _row("a", "deepmapping", 150.0),
        _row("a", "strep", 140.0),
        _row("b", "deepmapping", 5.0),
        _row("b", "strep", 120.0),
    ]
    assert claim1(rows).verdict == "does not hold"
    assert claim2(rows).verdict == "does not hold"
    # no DeepMapping failure at all: nothing to rescue
    rows = [_row("b", "deepmapping", 5.0), _row("b", "strep", 30.0)]
    assert claim1(rows).verdict == "does not hold"
    assert claim2(rows).verdict == "holds partly"


def test_full_plan_is_sized_and_the_cli_knows_the_command(shared_data: Path) -> None:
    full = estimate(build_runs(PLANS["full"], shared_data))
    assert 20 * 60 <= full["total"] <= 50 * 60, full
    quick = estimate(build_runs(PLANS["quick"], shared_data))
    assert quick["total"] <= 180, quick
    args = make_parser().parse_args(["reproduce", "--quick", "--out", "x", "--docs", "y.md"])
    assert args.quick and args.out == "x" and str(args.docs) == "y.md"


def test_without_matplotlib_the_figures_name_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """matplotlib is the ``bench`` extra, not a core dependency: its absence is one line naming it."""
    import sys

    from strep_bench.extras import MissingExtra, pyplot
    from strep_cli import main
    from strep_core.errors import StrepError

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    with pytest.raises(MissingExtra, match=r"pip install 'strep-studio\[bench\]'") as info:
        pyplot()
    assert isinstance(info.value, StrepError) and "\n" not in str(info.value)
    # before any run: the command names the extra at once, with exit code 2
    assert main(["reproduce", "--quick", "--out", str(tmp_path), "--data", str(tmp_path / "absent")]) == 2
    assert "strep-studio[bench]" in capsys.readouterr().err
