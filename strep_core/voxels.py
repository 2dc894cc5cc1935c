"""One point per grid cell: the subsampling every front end shares (scan matcher, submaps,
the probe, the LiDAR axis)."""

from __future__ import annotations

import numpy as np


def first_per_cell(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices, in order, of the first point of each ``cell``-sized voxel of ``points`` ``(N, D)``.

    2D keys are folded into one integer (exact while a log spans under two million cells a
    side); 3D keys are compared whole."""
    keys = np.floor(points / cell).astype(np.int64)
    if keys.shape[1] == 2:
        _, first = np.unique(keys[:, 0] * 2_000_003 + keys[:, 1], return_index=True)
    else:
        _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)
