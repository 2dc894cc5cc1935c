"""The batches of the learned loop: how many frames a step takes and in which order.

A sequence of up to `AUTO_BATCH_FRAMES` frames is one batch; a longer one is cut into batches
overlapping by the Chamfer window, each visited in turn (docs/design/whole-logs.md). The data
is packed by `strep_core.prepare`, a step's pairs are planned by `strep_core.plan`.
"""

from __future__ import annotations

import numpy as np

from strep_core.config import RunConfig

# Frames per step of a long sequence under ``optim.batch_frames="auto"``: every benchmark window and
# sample (up to 256 frames, v1_pose0) keeps one batch of all frames; whole logs get bounded
# batches, so the refinement's peak memory stays flat in the log's length (docs/design/whole-logs.md).
AUTO_BATCH_FRAMES = 256


def batch_size(num_frames: int, batch_frames: int | str | None) -> int | None:
    """Frames per batch of a ``num_frames`` sequence: ``None`` for one batch of all frames.

    ``"auto"``: all frames up to `AUTO_BATCH_FRAMES`, else batches of that many.
    """
    if batch_frames == "auto":
        return None if num_frames <= AUTO_BATCH_FRAMES else AUTO_BATCH_FRAMES
    assert batch_frames is None or isinstance(batch_frames, int)
    return None if batch_frames is None or batch_frames >= num_frames else batch_frames


def total_steps(num_frames: int, config: RunConfig) -> int:
    """Optimiser steps of a run: ``optim.iterations`` per batch, so every frame gets as many
    updates however the sequence is cut (each step takes the next batch in turn)."""
    batches = batch_schedule(num_frames, batch_size(num_frames, config.optim.batch_frames), config.loss.window)
    return config.optim.iterations * len(batches)


def batch_schedule(num_frames: int, batch: int | None, window: int) -> list[np.ndarray]:
    """Contiguous batches of frames covering the sequence, overlapping by ``window`` frames.

    Consecutive batches share ``window`` frames so every temporal neighbour pair lies
    inside at least one batch. ``None`` or ``batch >= num_frames``: one batch of all frames.
    """
    if batch is None or batch >= num_frames:
        return [np.arange(num_frames)]
    stride = max(1, batch - window)
    starts = [*list(range(0, num_frames - batch, stride)), num_frames - batch]
    return [np.arange(s, s + batch) for s in starts]
