"""Rerun recordings of registration runs: a sink that writes one ``.rrd`` per job or comparison.

A `RerunRecorder` is a sink (``emit(event)``) of `strep_core.events`. It owns its own
``rerun.RecordingStream`` (never the global one), with an explicit recording id, streaming to
a temporary file beside ``path`` that is renamed into place by `close` (or by the last
`ResultEvent`), so a reader never sees a half-written recording.

Entity paths (``<run>`` is the run's label reduced to ``[A-Za-z0-9_-]``, by default the method):

====================================== ========= ==========================================
path                                   when      what
====================================== ========= ==========================================
``world``                              static    view coordinates (z up)
``world/<run>``                        static    Transform3D: the panel's x offset
``world/<run>/label``                  static    Points3D: one point labelled with the run
``world/<run>/frames``                 iteration Transform3D: display anchor ``G_0 inv(T_0)``
``world/<run>/frames/frame_<k>``       static    Points3D: frame k's local points, its colour
``world/<run>/frames/frame_<k>``       iteration Transform3D: the estimated pose ``T_k``
``world/<run>/trajectory``             iteration LineStrips3D: estimated positions
``world/<run>/map``                    iteration Points3D: fused map every ``map_every``
``world/<run>/ground_truth/trajectory`` static   LineStrips3D, when ground truth is known
``world/<run>/ground_truth/map``       static    Points3D (grey), when ground truth is known
``metrics/<run>/loss/<term>``          iteration Scalars (``total`` included)
``metrics/<run>/ate``                  iteration Scalars, when ground truth is known
``summary/<run>``                      static    TextDocument: the final metrics
``logs/<run>``                         iteration TextLog: stages, start, result
====================================== ========= ==========================================

Timelines: ``iteration`` (sequence: the event's iteration, the result's count at the end)
and ``elapsed`` (duration: seconds since the run started). Frames move through their
transforms, so each frame's points are logged once. The default blueprint opens a 3D view
of ``world`` (the fused-map snapshots hidden, the live frames shown) beside time-series
views of the losses and the ATE and the summary text.

Telemetry: writing a recording sends nothing anywhere; analytics live in the Rerun *viewer*.
`disable_rerun_telemetry` switches off what can be switched off before a viewer is started.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

# OpenTelemetry tracing of the Rerun SDK stays off unless someone explicitly asked for it
# (rerun reads this when imported). Analytics: see `disable_rerun_telemetry`.
os.environ.setdefault("TELEMETRY_ENABLED", "false")

import rerun as rr
import rerun.blueprint as rrb

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
from strep_core.events import Event, ResultEvent, StageEvent, StartEvent, progress_events
from strep_core.sequence import Sequence

log = logging.getLogger(__name__)

APPLICATION_ID = "strep-studio"
ITERATION = "iteration"
ELAPSED = "elapsed"
GT_COLOR = (150, 150, 150)
TRAJECTORY_COLORS = [(230, 80, 40), (40, 120, 230), (40, 170, 90), (170, 70, 200), (220, 170, 30)]


def disable_rerun_telemetry(*, write_viewer_config: bool = False) -> None:
    """Switch off Rerun's telemetry for this process and the viewers it starts.

    * ``TELEMETRY_ENABLED=false``: the SDK's OpenTelemetry tracing (set at import of this
      module too, unless already set).
    * ``write_viewer_config=True`` runs the documented opt-out ``rerun analytics disable``
      (the bundled CLI), which writes ``analytics_enabled: false`` into the user's
      ``~/.config/rerun/analytics.json``: native viewers and the web-viewer server started
      from this machine then send no usage data. Rerun 0.41 has no environment variable for
      this (its README's ``RERUN_ANALYTICS=0`` is not read by the 0.41 binary; only
      ``FORCE_RERUN_ANALYTICS`` and ``CI`` are). The wasm viewer in a browser reports from the
      browser; a page that embeds it should restrict ``connect-src`` in its CSP.
    """
    os.environ["TELEMETRY_ENABLED"] = "false"
    if write_viewer_config:
        subprocess.run(
            [sys.executable, "-m", "rerun", "analytics", "disable"],
            check=True,
            capture_output=True,
            timeout=60,
        )


# --------------------------------------------------------------------------------------------
# The recorder


@dataclass
class _Run:
    """State of one run (one sub-tree) in a recording."""

    label: str
    key: str
    index: int
    method: str | None = None
    started: bool = False
    finished: bool = False
    events: int = 0
    last_iteration: int = -1
    last_map_iteration: int | None = None
    last_poses: np.ndarray | None = None  # (K, 3|6) pose vectors as logged
    bbox: tuple[np.ndarray, np.ndarray] | None = None
    iterations: list[int] = field(default_factory=list)


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
        self._pending: list[Event] = []  # events of the `emit` run before its StartEvent names it
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
                if not isinstance(event, StartEvent):
                    self._pending.append(event)
                    return
                self._default_label = event.method
                pending, self._pending = self._pending, []
                for ev in pending:
                    self._emit(self._default_label, ev)
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
            if self.autoclose and isinstance(event, ResultEvent) and self._all_finished():
                self.close()

    def _all_finished(self) -> bool:
        expected = self._expected if self._expected is not None else [self._default_label]
        return all(lab in self._runs and self._runs[lab].finished for lab in expected)

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
        rec = self.rec
        run.events += 1
        if isinstance(event, StartEvent):
            run.method, run.started = event.method, True
            rec.set_time(ITERATION, sequence=0)
            rec.set_time(ELAPSED, duration=0.0)
            rec.log(
                f"logs/{run.key}",
                rr.TextLog(
                    f"{run.label}: {event.method} on {event.sequence} ({event.frames} frames, {event.dims}D, "
                    f"{event.total_iterations} iterations planned, initial guess {event.initial_guess})"
                ),
            )
            return
        if isinstance(event, StageEvent):
            rec.set_time(ITERATION, sequence=max(run.last_iteration, 0))
            rec.set_time(ELAPSED, duration=event.elapsed)
            rec.log(f"logs/{run.key}", rr.TextLog(f"{run.label}: stage {event.stage}"))
            return
        if isinstance(event, ResultEvent):
            iteration = max(event.iterations, run.last_iteration, 0)
            rec.set_time(ITERATION, sequence=iteration)
            rec.set_time(ELAPSED, duration=event.wall_seconds)
            poses = np.asarray(event.poses, dtype=np.float64)
            if run.last_poses is None or iteration != run.last_iteration or not np.array_equal(poses, run.last_poses):
                self._log_poses(run, iteration, poses, final=True)
            elif run.last_map_iteration != iteration:
                self._log_map(run, iteration, poses)
            ate = event.metrics.get("ate")
            if isinstance(ate, (int, float)):
                rec.log(f"metrics/{run.key}/ate", rr.Scalars(float(ate)))
            rec.log(
                f"summary/{run.key}",
                rr.TextDocument(_summary(run, event), media_type=rr.MediaType.MARKDOWN),
                static=True,
            )
            rec.log(f"logs/{run.key}", rr.TextLog(f"{run.label}: finished after {event.wall_seconds:.2f} s"))
            run.finished = True
            return
        # IterationEvent
        rec.set_time(ITERATION, sequence=event.iteration)
        rec.set_time(ELAPSED, duration=event.elapsed)
        for term, value in event.losses.items():
            rec.log(f"metrics/{run.key}/loss/{safe_name(term)}", rr.Scalars(float(value)))
        if event.ate is not None:
            rec.log(f"metrics/{run.key}/ate", rr.Scalars(float(event.ate)))
        if event.poses is not None:
            self._log_poses(run, event.iteration, np.asarray(event.poses, dtype=np.float64), final=False)

    def _log_poses(self, run: _Run, iteration: int, vectors: np.ndarray, *, final: bool) -> None:
        rec, root = self.rec, f"world/{run.key}"
        est = poses_to_matrices(vectors)
        anchor = display_anchor(est, self.scene.ground_truth)
        rec.log(f"{root}/frames", rr.Transform3D(translation=anchor[:3, 3], mat3x3=anchor[:3, :3]))
        for k, pose in enumerate(est):
            rec.log(f"{root}/frames/frame_{k}", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        shown = anchor[None] @ est
        rec.log(f"{root}/trajectory", rr.LineStrips3D.from_fields(strips=[shown[:, :3, 3]]))
        run.last_poses, run.last_iteration = vectors, iteration
        if not run.iterations or run.iterations[-1] != iteration:
            run.iterations.append(iteration)
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


def default_blueprint(keys: list[str]) -> rrb.Blueprint:
    """3D view of ``world`` (map snapshots hidden) beside loss, ATE and summary views."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                name="Registration",
                origin="world",
                overrides={f"world/{k}/map": rrb.EntityBehavior(visible=False) for k in keys},
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    name="Loss", origin="metrics", contents=[f"+ metrics/{k}/loss/**" for k in keys] or "$origin/**"
                ),
                rrb.TimeSeriesView(name="ATE", origin="metrics", contents=[f"+ metrics/{k}/ate" for k in keys]),
                rrb.TextDocumentView(name="Summary", origin="summary"),
                row_shares=[2, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def _unit_box() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(3), np.ones(3)


def _summary(run: _Run, event: ResultEvent) -> str:
    lines = [f"### {run.label}", "", "| metric | value |", "| --- | --- |"]
    for name, value in event.metrics.items():
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


# --------------------------------------------------------------------------------------------
# Reading back


@dataclass
class RunRecording:
    """One run as read back from a recording.

    Attributes:
        key: the run's entity key (``world/<key>``).
        label: its label (from the label point), when present.
        iterations: distinct ``iteration`` values at which poses were logged, ascending.
        last_poses: ``(K, 4, 4)`` float64: each frame's transform at the last logged
            iteration (the estimated local -> world poses, float32 precision).
        scalars: ``loss/<term>`` and ``ate`` -> ``(iterations, values)``.
        map_iterations: iterations at which a fused map was logged.
        offset: ``(3,)`` the panel's offset in ``world`` (static, the latest layout).
    """

    key: str
    label: str | None
    iterations: list[int]
    last_poses: np.ndarray
    scalars: dict[str, tuple[np.ndarray, np.ndarray]]
    map_iterations: list[int]
    offset: np.ndarray


@dataclass
class RecordingSummary:
    """What a ``.rrd`` written by a recorder holds."""

    application_id: str
    recording_id: str
    entity_paths: list[str]
    runs: dict[str, RunRecording]
    has_blueprint: bool
    views: list[str] = field(default_factory=list)


def read_recording(path: str | Path) -> RecordingSummary:
    """Read a recording back with Rerun's own reader (`rerun.chunk.RrdReader`)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    stores = reader.recordings()
    if not stores:
        raise ValueError(f"{path} holds no recording")
    store = stores[0]
    paths: set[str] = set()
    # (key, k) -> (iteration, row id, translation, mat3x3)
    last: dict[tuple[str, int], tuple[int, bytes, list[float], list[float]]] = {}
    iterations: dict[str, set[int]] = {}
    map_its: dict[str, set[int]] = {}
    labels: dict[str, str] = {}
    offsets: dict[str, tuple[bytes, list[float]]] = {}
    scalars: dict[tuple[str, str], list[tuple[int, bytes, float]]] = {}
    for chunk in reader.stream(store=store):
        entity = chunk.entity_path.lstrip("/")
        paths.add(entity)
        parts = entity.split("/")
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if chunk.is_static:  # the latest static write wins, as in the viewer
            rows = [bytes(r) for r in batch.column("rerun.controls.RowId").to_pylist()]
            if len(parts) == 3 and parts[0] == "world" and parts[2] == "label" and "Points3D:labels" in names:
                for row in batch.column("Points3D:labels").to_pylist():
                    if row:
                        labels[parts[1]] = row[0]
            if len(parts) == 2 and parts[0] == "world" and "Transform3D:translation" in names:
                for rid, t in zip(rows, batch.column("Transform3D:translation").to_pylist(), strict=True):
                    if t and (parts[1] not in offsets or rid > offsets[parts[1]][0]):
                        offsets[parts[1]] = (rid, t[0])
            continue
        if ITERATION not in names:
            continue
        its = batch.column(ITERATION).to_pylist()
        rows = [bytes(r) for r in batch.column("rerun.controls.RowId").to_pylist()]
        if len(parts) == 4 and parts[0] == "world" and parts[2] == "frames" and parts[3].startswith("frame_"):
            key, k = parts[1], int(parts[3].removeprefix("frame_"))
            trans = batch.column("Transform3D:translation").to_pylist()
            mats = batch.column("Transform3D:mat3x3").to_pylist()
            for it, rid, t, m in zip(its, rows, trans, mats, strict=True):
                if it is None or not t or not m:
                    continue
                iterations.setdefault(key, set()).add(it)
                cur = last.get((key, k))
                if cur is None or (it, rid) > (cur[0], cur[1]):
                    last[(key, k)] = (it, rid, t[0], m[0])
        elif len(parts) == 3 and parts[0] == "world" and parts[2] == "map" and "Points3D:positions" in names:
            map_its.setdefault(parts[1], set()).update(i for i in its if i is not None)
        elif len(parts) >= 3 and parts[0] == "metrics" and "Scalars:scalars" in names:
            name = "/".join(parts[2:])
            values = batch.column("Scalars:scalars").to_pylist()
            for it, rid, v in zip(its, rows, values, strict=True):
                if it is not None and v:
                    scalars.setdefault((parts[1], name), []).append((it, rid, float(v[0])))

    runs: dict[str, RunRecording] = {}
    for key in sorted(iterations):
        ks = sorted(k for (kk, k) in last if kk == key)
        poses = np.zeros((len(ks), 4, 4))
        for i, k in enumerate(ks):
            _, _, t, m = last[(key, k)]
            poses[i, :3, :3] = np.asarray(m, dtype=np.float64).reshape(3, 3, order="F")
            poses[i, :3, 3] = t
            poses[i, 3, 3] = 1.0
        curves = {}
        for (kk, name), pts in scalars.items():
            if kk == key:
                pts.sort()
                curves[name] = (np.array([p[0] for p in pts], np.float64), np.array([p[2] for p in pts], np.float64))
        runs[key] = RunRecording(
            key=key,
            label=labels.get(key),
            iterations=sorted(iterations[key]),
            last_poses=poses,
            scalars=curves,
            map_iterations=sorted(map_its.get(key, set())),
            offset=np.asarray(offsets[key][1] if key in offsets else np.zeros(3), dtype=np.float64),
        )
    views: list[str] = []
    for bp in reader.blueprints()[-1:]:  # the latest blueprint sent
        for chunk in reader.stream(store=bp):
            batch = chunk.to_record_batch()
            if "ViewBlueprint:display_name" in batch.schema.names:
                views += [v[0] for v in batch.column("ViewBlueprint:display_name").to_pylist() if v]
    return RecordingSummary(
        application_id=store.application_id,
        recording_id=store.recording_id,
        entity_paths=sorted(paths),
        runs=runs,
        has_blueprint=bool(reader.blueprints()),
        views=sorted(set(views)),
    )
