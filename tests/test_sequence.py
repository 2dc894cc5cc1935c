"""The Sequence model: validation errors, selections, summary."""

from __future__ import annotations

import numpy as np
import pytest

from strep_core import geometry as g
from strep_core.errors import SequenceError
from strep_core.sequence import FrameSelection, Sequence


def frames(k: int = 5, n: int = 10, d: int = 2) -> list[np.ndarray]:
    return [np.random.default_rng(i).normal(size=(n, d)) for i in range(k)]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"frames": frames(1)}, "at least 2 frames"),
        ({"frames": [*frames(2), np.full((10, 2), np.nan)]}, "non-finite"),
        ({"frames": [*frames(2), np.array([[0.0, np.inf]] * 5)]}, "non-finite"),
        ({"frames": [*frames(2), np.zeros((2, 2))]}, "frame 2 has 2 points"),
        ({"frames": [*frames(2, d=2), *frames(1, d=3)]}, "mix dimensions"),
        ({"frames": [np.zeros((10, 4))] * 3}, "expected (N, 2) or (N, 3)"),
        ({"frames": frames(3), "poses": g.identity(2, 4)}, "4 poses for 3 frames"),
        ({"frames": frames(3), "poses": g.identity(3, 3)}, "expected (3, 3, 3)"),
        ({"frames": frames(3), "initial_poses": np.full((3, 3, 3), np.nan)}, "initial poses contain non-finite"),
        ({"frames": frames(3), "unit": "furlong"}, "unit must be"),
        ({"frames": frames(3), "origins": np.zeros((2, 2))}, "origins have shape"),
    ],
)
def test_validation_errors_are_typed_and_clear(kwargs: dict, message: str) -> None:
    with pytest.raises(SequenceError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Sequence(**kwargs)


def test_selection_keeps_original_indices() -> None:
    seq = Sequence(frames=frames(10), poses=g.identity(2, 10), indices=np.arange(100, 110))
    sub = seq.select("2:9:3")
    assert sub.indices.tolist() == [102, 105, 108]
    assert len(sub.poses) == 3
    np.testing.assert_array_equal(sub.frames[1], seq.frames[5])
    # selections compose and still keep the very first input's indices
    assert sub.select("1:").indices.tolist() == [105, 108]
    with pytest.raises(SequenceError, match="keeps 1 of 10"):
        seq.select("3:4")


@pytest.mark.parametrize(
    ("text", "expected"),
    [("0:100", (0, 100, None)), ("::4", (None, None, 4)), ("10:", (10, None, None)), ("", (None, None, None))],
)
def test_frame_selection_parse(text: str, expected: tuple) -> None:
    sel = FrameSelection.parse(text)
    assert (sel.start, sel.stop, sel.step) == expected


@pytest.mark.parametrize("bad", ["a:b", "1:2:0", "1:2:3:4", "5", "1:-2:-1"])
def test_frame_selection_rejects_bad_text(bad: str) -> None:
    with pytest.raises(SequenceError):
        FrameSelection.parse(bad)


def test_scale_is_median_range() -> None:
    pts = [np.array([[3.0, 4.0], [6.0, 8.0], [0.0, 1.0]]), np.array([[5.0, 0.0], [0.0, 5.0], [1.0, 0.0]])]
    assert Sequence(frames=pts).scale() == pytest.approx(5.0)
    s = Sequence(frames=pts, unit="px").summary()
    assert s == {
        "name": "sequence",
        "frames": 2,
        "dims": 2,
        "points": 6,
        "unit": "px",
        "has_ground_truth": False,
        "has_initial_guess": False,
    }
