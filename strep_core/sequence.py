"""The `Sequence`: a temporal sequence of local point clouds, the input of every method."""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from strep_core.errors import ConfigError, SequenceError

Unit = Literal["px", "m"]

MIN_POINTS = 3  # a frame needs at least this many points to be registered at all
MAX_SELECTION_CHARS = 64  # a frame selection ``start:stop[:step]`` is never longer
MAX_INDEX_DIGITS = 18  # each index of a selection fits an int64 (and int() never meets its digit limit)
MAX_COORDINATE = 1e9  # |coordinate| of any point, origin or pose translation, in the sequence's unit
MIN_FRAMES = 2  # a sequence (and a frame selection of one) has at least this many frames
RIGID_TOLERANCE = 1e-2  # largest entry of R R^T - I accepted in a pose (7-Scenes' own poses are off by 1.4e-4)


class FrameSelectionError(ConfigError, SequenceError):
    """A frame selection that is malformed or keeps fewer than `MIN_FRAMES` frames: an invalid
    option (a `ConfigError`, 422 in the API) about a sequence (still a `SequenceError`)."""


@dataclass(frozen=True)
class FrameSelection:
    """A Python-style slice over the frames of an input: ``start:stop[:step]``.

    Parsed from strings like ``"0:100"``, ``"300:400:2"``, ``"::4"`` or ``"10:"``.
    """

    start: int | None = None
    stop: int | None = None
    step: int | None = None

    @classmethod
    def parse(cls, text: str | FrameSelection | slice | None) -> FrameSelection:
        """Parse ``start:stop[:step]``; ``None`` or ``""`` selects every frame."""
        if text is None:
            return cls()
        if isinstance(text, FrameSelection):
            return text
        if isinstance(text, slice):
            return cls(text.start, text.stop, text.step)
        text = text.strip()
        if not text:
            return cls()
        if len(text) > MAX_SELECTION_CHARS or not re.fullmatch(r"-?\d*:-?\d*(:-?\d*)?", text):
            shown = text if len(text) <= MAX_SELECTION_CHARS else text[:MAX_SELECTION_CHARS] + "..."
            raise FrameSelectionError(f"frame selection {shown!r} is not of the form start:stop[:step]")
        if any(len(p.lstrip("-")) > MAX_INDEX_DIGITS for p in text.split(":")):
            raise FrameSelectionError(f"frame selection {text!r}: indices have at most {MAX_INDEX_DIGITS} digits")
        parts = [int(p) if p else None for p in text.split(":")]
        parts += [None] * (3 - len(parts))
        if parts[2] is not None and parts[2] <= 0:
            raise FrameSelectionError(f"frame selection {text!r}: step must be positive")
        return cls(*parts)

    def indices(self, n: int) -> np.ndarray:
        """The selected indices among ``n`` input frames, as an int64 array."""
        return np.arange(n, dtype=np.int64)[slice(self.start, self.stop, self.step)]

    def keep(self, n: int) -> np.ndarray:
        """`indices` of a selection that must keep at least `MIN_FRAMES` of ``n`` frames.

        Raises:
            FrameSelectionError: a selection (not every frame) keeping fewer; a sequence that
                has too few frames by itself is left to `Sequence.validate` to report.
        """
        idx = self.indices(n)
        if len(idx) < MIN_FRAMES and len(idx) < n:
            raise FrameSelectionError(
                f"frame selection {self} keeps {len(idx)} of {n} frames; at least {MIN_FRAMES} are needed"
            )
        return idx

    def __str__(self) -> str:
        s = f"{'' if self.start is None else self.start}:{'' if self.stop is None else self.stop}"
        return s if self.step is None else f"{s}:{self.step}"


@dataclass
class Sequence:
    """Frames of points in their local sensor coordinates, with optional ground truth.

    Attributes:
        frames: ``K`` arrays of shape ``(N_i, D)``, float64, each in its sensor's frame
            (``N_i`` may differ between frames; ``D`` is 2 or 3).
        name: a short name for tables and file names.
        unit: unit of every length: ``"px"`` (map pixels) or ``"m"``.
        origins: ``(K, D)`` sensor origin of each frame in its local coordinates (the start
            of every ray, for free-space sampling); zeros by default.
        poses: optional ``(K, D+1, D+1)`` ground-truth poses, local -> world.
        initial_poses: optional ``(K, D+1, D+1)`` initial guess given with the data
            (odometry), local -> world.
        indices: ``(K,)`` each frame's index in the original input (kept by selections).
        colors: optional ``K`` arrays ``(N_i, 3)`` uint8, for viewers only.
        meta: free-form provenance (source path, reader, parameters).
    """

    frames: list[np.ndarray]
    name: str = "sequence"
    unit: Unit = "m"
    origins: np.ndarray | None = None
    poses: np.ndarray | None = None
    initial_poses: np.ndarray | None = None
    indices: np.ndarray | None = None
    colors: list[np.ndarray] | None = None
    meta: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for i, f in enumerate(self.frames):
            _check_real(f, f"frame {i}")
        for attr in ("origins", "poses", "initial_poses"):
            _check_real(getattr(self, attr), attr.replace("_", " "))
        self.frames = [np.ascontiguousarray(f, dtype=np.float64) for f in self.frames]
        k = len(self.frames)
        if self.origins is None and k:
            self.origins = np.zeros((k, self.frames[0].shape[-1] if self.frames[0].ndim == 2 else 2))
        if self.indices is None:
            self.indices = np.arange(k, dtype=np.int64)
        self.indices = np.asarray(self.indices, dtype=np.int64)
        if self.origins is not None:
            self.origins = np.asarray(self.origins, dtype=np.float64)
        for attr in ("poses", "initial_poses"):
            value = getattr(self, attr)
            if value is not None:
                setattr(self, attr, np.asarray(value, dtype=np.float64))
        self.validate()

    # ----------------------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        """Spatial dimension D (2 or 3)."""
        return int(self.frames[0].shape[1])

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def num_points(self) -> int:
        """Total number of points over all frames."""
        return int(sum(len(f) for f in self.frames))

    @property
    def has_ground_truth(self) -> bool:
        return self.poses is not None

    def validate(self) -> None:
        """Raise `SequenceError` with a clear message if anything is malformed."""
        k = len(self.frames)
        if k < MIN_FRAMES:
            raise SequenceError(f"a sequence needs at least {MIN_FRAMES} frames, got {k}")
        dims = set()
        for i, f in enumerate(self.frames):
            if f.ndim != 2 or f.shape[1] not in (2, 3):
                raise SequenceError(f"frame {i} has shape {f.shape}; expected (N, 2) or (N, 3)")
            dims.add(f.shape[1])
            if len(f) < MIN_POINTS:
                raise SequenceError(f"frame {i} has {len(f)} points; at least {MIN_POINTS} are needed")
            if not np.isfinite(f).all():
                raise SequenceError(f"frame {i} contains non-finite values (NaN or inf)")
            _check_range(f, f"frame {i}")
        if len(dims) > 1:
            raise SequenceError(f"frames mix dimensions {sorted(dims)}; all must be 2D or 3D")
        d = dims.pop()
        if self.unit not in ("px", "m"):
            raise SequenceError(f"unit must be 'px' or 'm', not {self.unit!r}")
        assert self.origins is not None and self.indices is not None
        if self.origins.shape != (k, d):
            raise SequenceError(f"origins have shape {self.origins.shape}; expected {(k, d)}")
        if not np.isfinite(self.origins).all():
            raise SequenceError("sensor origins contain non-finite values")
        _check_range(self.origins, "sensor origins")
        if self.indices.shape != (k,):
            raise SequenceError(f"{len(self.indices)} frame indices for {k} frames")
        for attr in ("poses", "initial_poses"):
            value = getattr(self, attr)
            if value is None:
                continue
            if value.ndim != 3 or value.shape[1:] != (d + 1, d + 1):
                raise SequenceError(f"{attr} have shape {value.shape}; expected ({k}, {d + 1}, {d + 1})")
            if len(value) != k:
                raise SequenceError(f"{len(value)} {attr.replace('_', ' ')} for {k} frames")
            if not np.isfinite(value).all():
                raise SequenceError(f"{attr.replace('_', ' ')} contain non-finite values")
            _check_rigid(value, attr.replace("_", " "))
        if self.colors is not None and (
            len(self.colors) != k or any(len(c) != len(f) for c, f in zip(self.colors, self.frames, strict=True))
        ):
            raise SequenceError("colors must give one (N_i, 3) array per frame")

    def select(self, selection: str | FrameSelection | slice | None) -> Sequence:
        """A new sequence with the selected frames; original indices are kept."""
        sel = FrameSelection.parse(selection)
        idx = sel.keep(len(self))
        assert self.origins is not None and self.indices is not None
        return replace(
            self,
            frames=[self.frames[i] for i in idx],
            origins=self.origins[idx],
            poses=None if self.poses is None else self.poses[idx],
            initial_poses=None if self.initial_poses is None else self.initial_poses[idx],
            indices=self.indices[idx],
            colors=None if self.colors is None else [self.colors[i] for i in idx],
            meta={**self.meta, "selection": str(sel)},
        )

    def scale(self) -> float:
        """A characteristic length of the data: median distance of points from their sensor.

        Used to set data-dependent defaults (correspondence distances, voxel sizes) and to
        normalise network inputs, so methods work the same in pixels and in metres.
        """
        assert self.origins is not None
        step = max(1, len(self) // 32)
        d = np.concatenate(
            [np.linalg.norm(f - o, axis=1) for f, o in zip(self.frames[::step], self.origins[::step], strict=True)]
        )
        s = float(np.median(d))
        return s if s > 0 else 1.0

    def summary(self) -> dict[str, object]:
        """JSON-friendly description (for listings and metrics files)."""
        return {
            "name": self.name,
            "frames": len(self),
            "dims": self.dim,
            "points": self.num_points,
            "unit": self.unit,
            "has_ground_truth": self.has_ground_truth,
            "has_initial_guess": self.initial_poses is not None,
        }


def _check_real(value: object, what: str) -> None:
    """Refuse arrays of anything but real numbers (complex, strings, booleans) before float64 conversion
    would drop an imaginary part or parse text."""
    if value is None:
        return
    kind = np.asarray(value).dtype.kind
    if kind not in "iuf":
        raise SequenceError(f"{what} has values of type {np.asarray(value).dtype}; real numbers are needed")


def _check_range(values: np.ndarray, what: str) -> None:
    if values.size and float(np.abs(values).max()) > MAX_COORDINATE:
        raise SequenceError(
            f"{what} has a coordinate of {float(np.abs(values).max()):.3g}; coordinates must lie within "
            f"+-{MAX_COORDINATE:g} (in the sequence's unit)"
        )


def _check_rigid(poses: np.ndarray, what: str) -> None:
    """Each ``(D+1, D+1)`` pose must be rigid: last row ``0 .. 0 1``, an orthonormal rotation block
    with determinant +1 (to `RIGID_TOLERANCE`), a translation within `MAX_COORDINATE`."""
    d = poses.shape[-1] - 1
    last = np.zeros(d + 1)
    last[d] = 1.0
    rot = poses[:, :d, :d]
    row_err = np.abs(poses[:, d, :] - last).max(axis=1)
    orth_err = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(d)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    bad_row = np.flatnonzero(row_err > 1e-6)
    if len(bad_row):
        raise SequenceError(f"{what}: pose {bad_row[0]} is not rigid: its last row is not {'0 ' * d}1")
    bad_rot = np.flatnonzero(~(orth_err <= RIGID_TOLERANCE))
    if len(bad_rot):
        i = bad_rot[0]
        raise SequenceError(
            f"{what}: pose {i} is not rigid: its rotation block is not orthonormal "
            f"(R R^T differs from the identity by {orth_err[i]:.3g})"
        )
    bad_det = np.flatnonzero(det <= 0)
    if len(bad_det):
        i = bad_det[0]
        raise SequenceError(f"{what}: pose {i} is not rigid: its rotation block is a reflection (det {det[i]:.3g})")
    _check_range(poses[:, :d, d], what)
