"""The Rerun sink: `RerunRecorder` writes the runs it is fed into one ``.rrd`` file.

It owns its own ``rerun.RecordingStream`` (never the global one), with an explicit recording
id, streaming to a temporary file beside ``path`` that is renamed into place by `close` (or
by the last `ResultEvent`), so a reader never sees a half-written recording. Each run's
events go through `strep_core.runstate.apply`; the recorder draws the `Step` each one
makes (entity paths: `app.rrd`), so it reads no event itself and skips kinds it has no
reducer for. Frames move through their transforms, so each frame's points are logged once.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from app.rrd.blueprint import APPLICATION_ID, ELAPSED, GT_COLOR, ITERATION, TRAJECTORY_COLORS, default_blueprint
from app.viewer.scene import (
    SequenceScene,
    bbox,
    display_anchor,
    label_position,
    layout_panels,
    poses_to_matrices,
    safe_name,
    union_bbox,
)
from strep_core.events import Event, progress_events
from strep_core.runstate import History, RunState, apply
from strep_core.sequence import Sequence

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# The recorder


@dataclass
class _Run:
    """State of one run (one sub-tree) in a recording."""

    label: str
    key: str
    index: int
    # what the run is (float64 poses: the figures are written out; no replay, a short history)
    state: RunState = field(default_factory=lambda: RunState(history=History(4)))
    # what has been drawn
    drawn_iteration: int = -1
    drawn_poses: np.ndarray | None = None  # (K, 3|6) pose vectors as logged
    last_map_iteration: int | None = None
    bbox: tuple[np.ndarray, np.ndarray] | None = None


class RerunRecorder:
    """A sink writing the runs it is fed into one ``.rrd`` file.

    Use it directly as the sink of one run (``emit``), or call `sink` once per run of a
    comparison (`ComparisonRecorder` does this with the labels known upfront, so its panels
    and blueprint are laid out from the start). Thread-safe: runs may emit from different
    threads. ``emit`` never raises into the method (errors are logged and the recorder stops).

    Args:
        path: the ``.rrd`` to write; it appears only when the recorder is closed.
        recording_id: the recording id (the job or comparison id).
        sequence: the sequence the runs register (frames, ground truth).
        application_id: Rerun application id.
        label: name of the single run fed through `emit` (default: the method of its
            `StartEvent`).
        labels: runs expected (a comparison); the recording closes itself once each has
            delivered its `ResultEvent` (with ``autoclose``).
        map_every: log the fused map every this many iterations (and at the end).
        max_map_points: at most this many points per fused map snapshot.
        max_frame_points: at most this many points over all frames' static clouds.
        autoclose: close when the expected runs (one, or ``labels``) have all finished.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        recording_id: str,
        sequence: Sequence,
        application_id: str = APPLICATION_ID,
        label: str | None = None,
        labels: Iterable[str] | None = None,
        map_every: int = 5,
        max_map_points: int = 50_000,
        max_frame_points: int = 200_000,
        autoclose: bool = True,
    ) -> None:
        if map_every < 1:
            raise ValueError("map_every must be at least 1")
        self.path = Path(path)
        self.tmp_path = self.path.with_name(f".{self.path.name}.{os.getpid()}.{id(self):x}.tmp")
        self.recording_id = str(recording_id)
        self.application_id = application_id
        self.map_every = map_every
        self.max_map_points = max_map_points
        self.autoclose = autoclose
        self.closed = False
        self.failed: str | None = None
        self._lock = threading.RLock()
        self._runs: dict[str, _Run] = {}
        self._default_label = label
        self._pending: list[Event] = []  # events of the `emit` run before its start event names it
        self._naming = RunState(history=History(4))  # those events, reduced until the method is known
        self._expected = list(labels) if labels is not None else None
        self._blueprint_keys: tuple[str, ...] = ()

        self.scene = SequenceScene.from_sequence(sequence, max_points=max_frame_points)
        self._map_step = self.scene.fuse_step(max_map_points)
        self._map_colors = self.scene.point_colors()[:: self._map_step]
        self._slot_width = 0.0

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream(application_id, recording_id=self.recording_id)
        initial = [safe_name(x) for x in self._expected] if self._expected else []
        self.rec.save(self.tmp_path, default_blueprint=self._blueprint(initial) if initial else None)
        self._blueprint_keys = tuple(initial)
        self.rec.send_recording_name(f"{sequence.name} [{self.recording_id}]")
        self._log_world()
        for lab in self._expected or []:
            self._run(lab)
        if label is not None and self._expected is None:
            self._run(label)

    # ---- sinks -----------------------------------------------------------------------------
    def emit(self, event: Event) -> None:
        """Record an event of the single run (see ``label``)."""
        with self._lock:
            if self._default_label is None:
                self._pending.append(event)
                if apply(self._naming, event).method is None:
                    return
                self._default_label = self._naming.method
                pending, self._pending = self._pending, []
                for ev in pending:
                    self._emit(self._default_label, ev)
                return
            self._emit(self._default_label, event)

    def sink(self, label: str) -> _RunSink:
        """A sink for the run ``label`` (one per method of a comparison)."""
        with self._lock:
            self._run(label)
        return _RunSink(self, label)

    def _emit(self, label: str, event: Event) -> None:
        with self._lock:
            if self.closed or self.failed:
                return
            try:
                self._record(self._run(label), event)
            except Exception as exc:  # a sink must never break the method it watches
                self.failed = f"{type(exc).__name__}: {exc}"
                log.exception("rerun recording %s failed; no more events are recorded", self.path)
                return
            if self.autoclose and self._all_finished():
                self.close()

    def _all_finished(self) -> bool:
        expected = self._expected if self._expected is not None else [self._default_label]
        return all(lab in self._runs and self._runs[lab].state.finished for lab in expected)

    # ---- lifecycle -------------------------------------------------------------------------
    def close(self, *, discard: bool = False) -> Path | None:
        """Finish the file and rename it to ``path`` (or delete it with ``discard``).

        Idempotent. Returns ``path``, or ``None`` when discarded.
        """
        with self._lock:
            if self.closed:
                return None if discard or not self.path.exists() else self.path
            self.closed = True
            try:
                self.rec.flush()
            finally:
                self.rec.disconnect()
            if discard:
                self.tmp_path.unlink(missing_ok=True)
                return None
            os.replace(self.tmp_path, self.path)
            return self.path

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        # a failed or cancelled run still leaves a complete (partial) recording
        self.close()

    def runs(self) -> dict[str, str]:
        """Labels of the runs so far -> their entity key."""
        with self._lock:
            return {lab: r.key for lab, r in self._runs.items()}

    # ---- logging ---------------------------------------------------------------------------
    def _run(self, label: str) -> _Run:
        run = self._runs.get(label)
        if run is not None:
            return run
        key = safe_name(label)
        taken = {r.key for r in self._runs.values()}
        base, n = key, 2
        while key in taken:
            key, n = f"{base}_{n}", n + 1
        run = _Run(label=label, key=key, index=len(self._runs))
        self._runs[label] = run
        self._log_run_static(run)
        self._relayout()
        if key not in self._blueprint_keys:
            self._blueprint_keys = (*self._blueprint_keys, key)
            self.rec.send_blueprint(self._blueprint(list(self._blueprint_keys)), make_active=False, make_default=True)
        return run

    def _log_world(self) -> None:
        sc = self.scene
        z_up = sc.dims == 2 or sc.ground_truth is not None
        coords = rr.ViewCoordinates.RIGHT_HAND_Z_UP if z_up else rr.ViewCoordinates.RDF
        self.rec.log("world", coords, static=True)

    def _log_run_static(self, run: _Run) -> None:
        sc, rec, root = self.scene, self.rec, f"world/{run.key}"
        for k, (pts, color) in enumerate(zip(sc.frames, sc.colors, strict=True)):
            rec.log(
                f"{root}/frames/frame_{k}",
                rr.Points3D(pts, colors=color, radii=rr.Radius.ui_points(1.5)),
                static=True,
            )
        rec.log(
            f"{root}/map",
            rr.Points3D.from_fields(colors=self._map_colors, radii=rr.Radius.ui_points(1.5)),
            static=True,
        )
        color = TRAJECTORY_COLORS[run.index % len(TRAJECTORY_COLORS)]
        rec.log(
            f"{root}/trajectory",
            rr.LineStrips3D.from_fields(colors=color, radii=rr.Radius.ui_points(2.0)),
            static=True,
        )
        if sc.ground_truth is not None:
            gt_map = sc.fuse(sc.ground_truth, max_points=self.max_map_points)
            rec.log(
                f"{root}/ground_truth/trajectory",
                rr.LineStrips3D([sc.ground_truth[:, :3, 3]], colors=GT_COLOR, radii=rr.Radius.ui_points(1.5)),
                static=True,
            )
            rec.log(
                f"{root}/ground_truth/map",
                rr.Points3D(gt_map, colors=GT_COLOR, radii=rr.Radius.ui_points(1.0)),
                static=True,
            )
            run.bbox = sc.gt_bbox()
        rec.log(f"metrics/{run.key}/ate", rr.SeriesLines(colors=color, names=f"{run.label} ATE"), static=True)

    def _relayout(self) -> None:
        """Place every run's panel side by side (static transforms; the latest layout wins)."""
        runs = list(self._runs.values())
        boxes = [r.bbox if r.bbox is not None else _unit_box() for r in runs]
        offsets = layout_panels(boxes)
        self._slot_width = max(float(hi[0] - lo[0]) for lo, hi in boxes)
        for run, box, off in zip(runs, boxes, offsets, strict=True):
            self.rec.log(f"world/{run.key}", rr.Transform3D(translation=off), static=True)
            self.rec.log(
                f"world/{run.key}/label",
                rr.Points3D(
                    [label_position(box)], labels=[run.label], show_labels=True, radii=rr.Radius.ui_points(4.0)
                ),
                static=True,
            )

    def _record(self, run: _Run, event: Event) -> None:
        """Apply ``event`` to the run's state and draw the step it made."""
        step = apply(run.state, event).step
        if step is None:
            return  # a kind without a reducer: nothing to draw
        rec = self.rec
        rec.set_time(ITERATION, sequence=step.iteration)
        rec.set_time(ELAPSED, duration=step.elapsed)
        snap = step.snapshot
        if snap is not None and not step.final:
            for term, value in snap.losses.items():
                rec.log(f"metrics/{run.key}/loss/{safe_name(term)}", rr.Scalars(float(value)))
            if snap.ate is not None:
                rec.log(f"metrics/{run.key}/ate", rr.Scalars(float(snap.ate)))
            if snap.poses is not None and snap.poses is not run.drawn_poses:
                self._log_poses(run, snap.iteration, snap.poses, final=False)
        elif snap is not None:  # the result: the final poses (or map), the final ATE, the summary
            poses, it = snap.poses, step.iteration
            assert poses is not None
            if run.drawn_poses is None or it != run.drawn_iteration or not np.array_equal(poses, run.drawn_poses):
                self._log_poses(run, it, poses, final=True)
            elif run.last_map_iteration != it:
                self._log_map(run, it, poses)
            if snap.ate is not None:
                rec.log(f"metrics/{run.key}/ate", rr.Scalars(float(snap.ate)))
            rec.log(
                f"summary/{run.key}",
                rr.TextDocument(_summary(run), media_type=rr.MediaType.MARKDOWN),
                static=True,
            )
        if step.message is not None:
            rec.log(f"logs/{run.key}", rr.TextLog(f"{run.label}: {step.message}"))

    def _log_poses(self, run: _Run, iteration: int, vectors: np.ndarray, *, final: bool) -> None:
        rec, root = self.rec, f"world/{run.key}"
        est = poses_to_matrices(vectors)
        anchor = display_anchor(est, self.scene.ground_truth)
        rec.log(f"{root}/frames", rr.Transform3D(translation=anchor[:3, 3], mat3x3=anchor[:3, :3]))
        for k, pose in enumerate(est):
            rec.log(f"{root}/frames/frame_{k}", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        shown = anchor[None] @ est
        rec.log(f"{root}/trajectory", rr.LineStrips3D.from_fields(strips=[shown[:, :3, 3]]))
        run.drawn_poses, run.drawn_iteration = vectors, iteration
        due = run.last_map_iteration is None or iteration - run.last_map_iteration >= self.map_every
        if final or due:
            self._log_map(run, iteration, vectors, shown=shown)

    def _log_map(self, run: _Run, iteration: int, vectors: np.ndarray, *, shown: np.ndarray | None = None) -> None:
        if shown is None:
            est = poses_to_matrices(vectors)
            shown = display_anchor(est, self.scene.ground_truth)[None] @ est
        points = self.scene.fuse(shown, max_points=self.max_map_points)
        self.rec.log(f"world/{run.key}/map", rr.Points3D.from_fields(positions=points))
        run.last_map_iteration = iteration
        if self.scene.ground_truth is not None:
            return  # panels are laid out on the ground-truth map, which does not move
        first = run.bbox is None
        grown = union_bbox(run.bbox, bbox(points))
        assert grown is not None
        run.bbox = grown
        # re-place the panels only when a map outgrows the slots (no jitter at every snapshot)
        if first or float(grown[1][0] - grown[0][0]) > 1.05 * self._slot_width:
            self._relayout()

    # ---- blueprint -------------------------------------------------------------------------
    def _blueprint(self, keys: list[str]) -> rrb.Blueprint:
        return default_blueprint(keys)


class _RunSink:
    """The sink of one run of a `RerunRecorder`."""

    def __init__(self, recorder: RerunRecorder, label: str) -> None:
        self.recorder = recorder
        self.label = label

    def emit(self, event: Event) -> None:
        self.recorder._emit(self.label, event)


class ComparisonRecorder(RerunRecorder):
    """One ``.rrd`` holding several runs on one sequence side by side; ``sink(label)`` per run."""

    def __init__(
        self,
        path: str | Path,
        *,
        recording_id: str,
        sequence: Sequence,
        labels: Iterable[str],
        application_id: str = APPLICATION_ID,
        map_every: int = 5,
        max_map_points: int = 50_000,
        max_frame_points: int = 200_000,
        autoclose: bool = True,
    ) -> None:
        labels = list(labels)
        if not labels:
            raise ValueError("a comparison needs at least one label")
        if len(set(labels)) != len(labels):
            raise ValueError(f"comparison labels must be distinct: {labels}")
        super().__init__(
            path,
            recording_id=recording_id,
            sequence=sequence,
            application_id=application_id,
            labels=labels,
            map_every=map_every,
            max_map_points=max_map_points,
            max_frame_points=max_frame_points,
            autoclose=autoclose,
        )

    def emit(self, event: Event) -> None:
        raise TypeError("a ComparisonRecorder takes events through sink(label).emit(event)")


def _unit_box() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(3), np.ones(3)


def _summary(run: _Run) -> str:
    lines = [f"### {run.label}", "", "| metric | value |", "| --- | --- |"]
    for name, value in run.state.metrics.items():
        text = f"{value:.6g}" if isinstance(value, float) else str(value)
        lines.append(f"| {name} | {text} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Entry points for the CLI and the service


def cli_sink(path: str | Path, sequence: Sequence, method: str, run_id: str) -> RerunRecorder:
    """The sink behind ``strep run ... --rrd FILE``: one run named ``method``.

    It closes itself (the file appears) when the run's `ResultEvent` arrives; use it as a
    context manager so a failed or cancelled run still leaves its partial recording::

        with cli_sink(args.rrd, seq, config.method, run_id) as rrd:
            run(seq, config, sink=MultiSink([progress, rrd]))
    """
    return RerunRecorder(path, recording_id=run_id, sequence=sequence, label=method)


def write_recording(
    path: str | Path,
    *,
    recording_id: str,
    sequence: Sequence,
    runs: Mapping[str, Iterable[Any]],
    **options: Any,
) -> Path:
    """Write a recording after the fact from stored events (label -> events, in order).

    Events may be `Event` objects, dicts, JSON text or the job store's records (``kind`` and
    ``data``); entries that are not progress events (``status``...) are skipped.
    """
    if len(runs) == 1:
        ((label, events),) = runs.items()
        recorder: RerunRecorder = RerunRecorder(
            path, recording_id=recording_id, sequence=sequence, label=label, autoclose=False, **options
        )
        sinks = {label: recorder.sink(label)}
    else:
        recorder = ComparisonRecorder(
            path, recording_id=recording_id, sequence=sequence, labels=list(runs), autoclose=False, **options
        )
        sinks = {label: recorder.sink(label) for label in runs}
    with recorder:
        for label, events in runs.items():
            for ev in progress_events(events):
                sinks[label].emit(ev)
    if recorder.failed:
        raise RuntimeError(f"writing {path} failed: {recorder.failed}")
    return Path(path)
