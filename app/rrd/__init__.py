"""Rerun recordings (``.rrd``) of registration runs: one per job or comparison.

A `RerunRecorder` is a sink (``emit(event)``) of `strep_core.events`: it folds each run's
events into a `strep_core.runstate.RunState` and draws what the state says changed. Parts:
`app.rrd.recorder` (the sink, its runs and its file), `app.rrd.blueprint` (timelines,
colours, the default layout), `app.rrd.reader` (reading a recording back),
`app.rrd.telemetry` (Rerun's telemetry switched off).

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
"""

from __future__ import annotations

import os

# OpenTelemetry tracing of the Rerun SDK stays off unless someone explicitly asked for it
# (rerun reads this when imported). Analytics: see `disable_rerun_telemetry`.
os.environ.setdefault("TELEMETRY_ENABLED", "false")

from app.rrd.blueprint import APPLICATION_ID, default_blueprint
from app.rrd.reader import RecordingSummary, RunRecording, read_recording
from app.rrd.recorder import ComparisonRecorder, RerunRecorder, cli_sink, write_recording
from app.rrd.telemetry import disable_rerun_telemetry

__all__ = [
    "APPLICATION_ID",
    "ComparisonRecorder",
    "RecordingSummary",
    "RerunRecorder",
    "RunRecording",
    "cli_sink",
    "default_blueprint",
    "disable_rerun_telemetry",
    "read_recording",
    "write_recording",
]
