"""What the viewers show, computed with numpy only (no viser, no rerun).

Both views (the Rerun recorder, `app.rrd`, and the viser viewer, `app.viewer`) draw the
same things from the same run states (`strep_core.runstate`); this module holds the shared
drawing part:

* `SequenceScene`: a sequence prepared for drawing: each frame's local points padded to 3D
  (z = 0 in 2D), evenly strided to a point budget, float32; one colour per frame; the
  ground-truth poses as ``(K, 4, 4)``; the *display anchor* that places an estimate in the
  ground-truth world frame.
* pose conversions: pose vectors ``(K, 3|6)`` -> ``(K, 4, 4)`` -> positions and ``wxyz``.
* `layout_panels`: x offsets that put several runs side by side without overlap.

Display frame. A method's poses live in its own world frame (frame 0 at its initial guess,
often identity), while the ground truth lives in the data's world frame. When ground truth
is known, estimates are drawn as ``A @ T_k`` with ``A = G_0 @ inv(T_0)``: frame 0 is pinned
to its true pose, so the estimated map overlays the true one up to drift (and 3D rooms
stand upright). Without ground truth, ``A`` is the identity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from strep_core import geometry as g
from strep_core.result import frame_colors
from strep_core.sequence import Sequence

# --------------------------------------------------------------------------------------------
# Poses


def poses_to_matrices(pose_vectors: Any) -> np.ndarray:
    """Pose vectors ``(K, 3)`` (2D: x, y, theta) or ``(K, 6)`` (3D: t, axis-angle) -> ``(K, 4, 4)``.

    2D poses are embedded in SE(3) with z = 0 and a rotation about +z.
    """
    v = np.asarray(pose_vectors, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] not in (3, 6):
        raise ValueError(f"pose vectors must have shape (K, 3) or (K, 6), not {v.shape}")
    return g.to_se3(g.pose_from_vector(v))


def rotations_to_wxyz(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` as ``(w, x, y, z)`` (viser's order) of rotations ``(..., 3, 3)``."""
    xyzw = g.rotation_to_quaternion(rot)
    return np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1)


def display_anchor(estimate: np.ndarray, ground_truth: np.ndarray | None) -> np.ndarray:
    """``A = G_0 @ inv(T_0)`` ``(4, 4)``: moves an estimate ``(K, 4, 4)`` into the ground-truth world.

    The identity when there is no ground truth.
    """
    if ground_truth is None:
        return np.eye(4)
    return ground_truth[0] @ g.inverse(estimate[0])


# --------------------------------------------------------------------------------------------
# Point budgets


def stride_indices(counts: list[int], budget: int) -> list[np.ndarray]:
    """Per-frame indices keeping at most ``budget`` points in all, the same stride everywhere.

    Deterministic (an even stride), so a map drawn twice from the same poses is the same.
    """
    total = int(sum(counts))
    step = max(1, math.ceil(total / max(budget, 1)))
    return [np.arange(0, n, step) for n in counts]


# --------------------------------------------------------------------------------------------
# A sequence prepared for drawing


@dataclass
class SequenceScene:
    """A `Sequence` made ready for viewers.

    Attributes:
        frames: ``K`` arrays ``(n_k, 3)`` float32: local points (sensor frame), strided so
            that ``sum(n_k) <= max_points``; 2D frames have z = 0.
        colors: ``(K, 3)`` uint8, one colour per frame (hue along the sequence).
        ground_truth: ``(K, 4, 4)`` float64 ground-truth poses (local -> world) or ``None``.
        dims: 2 or 3.
        unit: ``"px"`` or ``"m"``.
        name: the sequence name.
        point_total: points in the full sequence (before striding).
    """

    frames: list[np.ndarray]
    colors: np.ndarray
    ground_truth: np.ndarray | None
    dims: int
    unit: str
    name: str
    point_total: int
    _gt_bbox: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @classmethod
    def from_sequence(cls, seq: Sequence, *, max_points: int) -> SequenceScene:
        """Prepare ``seq`` keeping at most ``max_points`` points over all frames."""
        idx = stride_indices([len(f) for f in seq.frames], max_points)
        frames = [
            np.ascontiguousarray(g.pad_points(f[i]), dtype=np.float32) for f, i in zip(seq.frames, idx, strict=True)
        ]
        colors = frame_colors(np.arange(len(seq)), len(seq))
        gt = None if seq.poses is None else g.to_se3(seq.poses)
        return cls(
            frames=frames,
            colors=colors,
            ground_truth=gt,
            dims=seq.dim,
            unit=seq.unit,
            name=seq.name,
            point_total=seq.num_points,
        )

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def num_points(self) -> int:
        """Points kept over all frames."""
        return int(sum(len(f) for f in self.frames))

    def point_colors(self) -> np.ndarray:
        """``(M, 3)`` uint8: each kept point's frame colour, in `fuse` order."""
        return np.repeat(self.colors, [len(f) for f in self.frames], axis=0)

    def display_poses(self, estimate: np.ndarray) -> np.ndarray:
        """``(K, 4, 4)``: the estimate in the display frame (see the module docstring)."""
        return display_anchor(estimate, self.ground_truth)[None] @ estimate

    def fuse(self, poses: np.ndarray, *, max_points: int | None = None) -> np.ndarray:
        """All kept points placed by ``poses (K, 4, 4)``: ``(M, 3)`` float32, in frame order.

        ``max_points`` strides the result further (the same stride as `point_colors` sliced
        with ``[::step]``, see `fuse_step`).
        """
        p = poses.astype(np.float32)
        out = np.concatenate([f @ r.T + t for f, r, t in zip(self.frames, p[:, :3, :3], p[:, :3, 3], strict=True)])
        return out[:: self.fuse_step(max_points)]

    def fuse_step(self, max_points: int | None) -> int:
        """The stride `fuse` applies for ``max_points``."""
        if max_points is None:
            return 1
        return max(1, math.ceil(self.num_points / max(max_points, 1)))

    def gt_bbox(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(min, max)`` ``(3,)`` of the ground-truth map, or ``None``."""
        if self.ground_truth is None:
            return None
        if self._gt_bbox is None:
            self._gt_bbox = bbox(self.fuse(self.ground_truth))
        return self._gt_bbox

    def marker_scale(self) -> float:
        """A length for drawing markers (axes, point sizes): 1% of the map's diagonal."""
        box = self.gt_bbox()
        if box is None:
            box = bbox(np.concatenate(self.frames))
        diag = float(np.linalg.norm(box[1] - box[0]))
        return max(diag, 1e-6) * 0.01


def bbox(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(min, max)`` ``(3,)`` float64 of ``(M, 3)`` points (zeros when empty)."""
    if len(points) == 0:
        return np.zeros(3), np.zeros(3)
    return points.min(0).astype(np.float64), points.max(0).astype(np.float64)


def union_bbox(
    a: tuple[np.ndarray, np.ndarray] | None, b: tuple[np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray] | None:
    if a is None:
        return b
    if b is None:
        return a
    return np.minimum(a[0], b[0]), np.maximum(a[1], b[1])


# --------------------------------------------------------------------------------------------
# Side-by-side layout


def layout_panels(boxes: list[tuple[np.ndarray, np.ndarray]], *, margin: float = 0.15) -> list[np.ndarray]:
    """Offsets ``(3,)`` placing panels left to right along +x without overlap.

    Every panel gets a slot as wide as the widest box plus ``margin`` times that width; panel
    ``i``'s box starts at ``i * slot`` (its minimum x is moved there), y and z are untouched.
    """
    if not boxes:
        return []
    width = max(float(hi[0] - lo[0]) for lo, hi in boxes)
    width = max(width, 1e-6)
    slot = width * (1.0 + margin)
    return [np.array([i * slot - lo[0] + boxes[0][0][0], 0.0, 0.0]) for i, (lo, _) in enumerate(boxes)]


def label_position(box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Where a panel's label goes: centred in x, just beyond the box in +y, on top in z."""
    lo, hi = box
    pad = 0.05 * float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-6))
    return np.array([(lo[0] + hi[0]) / 2.0, hi[1] + pad, hi[2]])


# --------------------------------------------------------------------------------------------
# Names


def safe_name(text: str) -> str:
    """``text`` reduced to ``[A-Za-z0-9_-]`` (other characters become ``_``), never empty."""
    out = "".join(c if c.isascii() and (c.isalnum() or c in "-_") else "_" for c in str(text))
    return out or "_"
