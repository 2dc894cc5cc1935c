"""Code that runs in child processes (started with the ``spawn`` context).

* `run_job`: one process per job. Loads the input, runs the method with a sink that sends
  every event through the job's pipe and a `app.recording.RerunRecorder` that records them
  into ``recording.rrd`` (recording id = job id), writes the other result files into the
  same temporary folder and renames it into place, then sends a final ``done`` message. The
  cancel flag is a ``multiprocessing.Event`` the core checks between iterations.
* `reader_loop`: a long-lived process that reads uploads to validate them, so a reader that
  crashes or runs away never takes the service with it.

This module imports only the standard library at the top: the child sets its thread limits
before numpy and torch are imported.

Messages on a job's pipe (pickled tuples):

* ``("event", kind, json, t)``: a `strep_core.events` event emitted at ``t`` (``time.time()``);
* ``("done", status, error, metrics, files)``: ``status`` is ``succeeded``, ``failed`` or
  ``cancelled``.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import multiprocessing
import multiprocessing.connection
import os
import shutil
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any

RECORDING = "recording.rrd"
THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _watch_parent() -> None:
    """Exit at once if the service process dies (a killed server must not leave orphans)."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os._exit(3)

    threading.Thread(target=watch, name="strep-parent-watch", daemon=True).start()


def _lower_priority(nice: int) -> None:
    """Yield the CPU to the service: optimisation is batch work, the API is interactive."""
    if nice > 0 and hasattr(os, "nice"):
        with contextlib.suppress(OSError):
            os.nice(nice)


def _limit_threads(threads: int) -> None:
    for name in THREAD_ENV:
        os.environ[name] = str(threads)


def _redirect_output(log_path: str | None) -> None:
    """Send this process's stdout and stderr (C libraries included) to the job's log file."""
    if not log_path:
        return
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)


def _import_plugins(plugins: list[str]) -> None:
    for name in plugins:
        importlib.import_module(name)


def _finite(value: Any) -> Any:
    """JSON-safe copy: non-finite floats become None, numpy scalars plain numbers."""
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if hasattr(value, "item") and callable(value.item) and getattr(value, "ndim", 1) == 0:
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


class PipeSink:
    """A `strep_core.events.Sink` that sends events through the job's pipe; never raises."""

    def __init__(self, conn: multiprocessing.connection.Connection) -> None:
        self.conn = conn
        self.broken = False

    def emit(self, event: Any) -> None:
        if self.broken:
            return
        try:
            self.conn.send(("event", event.kind, event.model_dump_json(), time.time()))
        except (OSError, ValueError):
            self.broken = True  # the service is gone; the parent watch ends this process


def load_source(
    source: str,
    selection: str | None,
    max_extract_bytes: int,
    extract_dir: str | None = None,
    max_points: int | None = None,
    options: dict[str, Any] | None = None,
) -> Any:
    """The `Sequence` behind a job's or an upload's source (``sample:NAME`` or a stored file).

    A stored file is read within the service's limits (bytes inflated, points; see
    `strep_core.io.limits`). A ``.zip`` is extracted under ``extract_dir`` (a folder the
    service sweeps), if given. ``options`` go to the reader (`RunConfig.data`).
    """
    from strep_core.pipeline import load_input

    if source.startswith("sample:"):
        return load_input(source, frames=selection, options=options)
    from strep_core.io import load_sequence

    if extract_dir is not None:
        Path(extract_dir).mkdir(parents=True, exist_ok=True)
    limits: dict[str, Any] = {"max_extract_bytes": max_extract_bytes}
    if max_points is not None:
        limits["max_points"] = max_points
    return load_sequence(source, frames=selection, extract_dir=extract_dir, **limits, **(options or {}))


def open_recorder(path: Path, job_id: str, seq: Any, config: Any) -> Any:
    """The job's Rerun recorder (a sink), or ``None`` when it cannot be opened.

    A recording is a by-product: failing to open one is written to the job's log and the job
    runs on without it. ``seq`` is the sequence as loaded; the recorder gets the frames the
    run registers (``config.frames`` applied, as `strep_core.methods.run` does).
    """
    try:
        from app.rrd import RerunRecorder, disable_rerun_telemetry

        disable_rerun_telemetry()
        frames = seq.select(config.frames) if config.frames else seq
        return RerunRecorder(path, recording_id=job_id, sequence=frames, label=config.method)
    except Exception:
        print("recording.rrd cannot be written:", file=sys.stderr)
        traceback.print_exc()
        return None


class GuardedSink:
    """Forwards events to a sink that must never fail the run: its first error is logged, then
    it gets no more events."""

    def __init__(self, sink: Any) -> None:
        self.sink = sink
        self.broken = False

    def emit(self, event: Any) -> None:
        if self.broken:
            return
        try:
            self.sink.emit(event)
        except Exception:
            self.broken = True
            traceback.print_exc()


def close_recorder(recorder: Any) -> None:
    """Close a recorder; a recording that cannot be finished is dropped (logged), never fatal."""
    try:
        recorder.close(discard=bool(recorder.failed))
    except Exception:
        traceback.print_exc()
        with contextlib.suppress(Exception):
            recorder.close(discard=True)
        Path(recorder.tmp_path).unlink(missing_ok=True)


def run_job(spec: dict[str, Any], conn: multiprocessing.connection.Connection, cancel: Any) -> None:
    """Entry point of a job's process. ``spec`` is built by `app.services.jobs.JobService`."""
    _watch_parent()
    _lower_priority(spec.get("nice", 0))
    _limit_threads(spec["threads"])
    _redirect_output(spec.get("log_path"))
    tmp_dir = Path(spec["tmp_dir"])
    out_dir = Path(spec["out_dir"])
    message: tuple[Any, ...]
    try:
        _import_plugins(spec.get("plugins", []))
        from strep_core.config import RunConfig
        from strep_core.errors import Cancelled, StrepError
        from strep_core.events import MultiSink, StageEvent
        from strep_core.methods import run
        from strep_core.pipeline import write_outputs

        try:
            config = RunConfig.model_validate_json(spec["config"])
            if config.threads is None:
                config = config.model_copy(update={"threads": spec["threads"]})
            started = time.perf_counter()
            PipeSink(conn).emit(StageEvent(stage="load", elapsed=0.0))
            seq = load_source(
                spec["source"],
                spec.get("selection"),
                spec["max_extract_bytes"],
                spec.get("extract_dir"),
                spec.get("max_points"),
                config.data.options(),
            )
            if spec.get("sequence_name"):  # an upload: its name, not its stored file's ("sequence")
                seq.name = spec["sequence_name"]
            if tmp_dir.exists():
                shutil.rmtree(tmp_dir)
            tmp_dir.mkdir(parents=True)
            recorder = open_recorder(tmp_dir / RECORDING, spec["job_id"], seq, config)
            sink = PipeSink(conn) if recorder is None else MultiSink([PipeSink(conn), GuardedSink(recorder)])
            try:
                result = run(seq, config, sink=sink, cancel=cancel)
            finally:
                if recorder is not None:
                    close_recorder(recorder)  # normally closed already by the ResultEvent
            PipeSink(conn).emit(StageEvent(stage="write", elapsed=time.perf_counter() - started))
            files = sorted({*write_outputs(result, tmp_dir), *([RECORDING] if (tmp_dir / RECORDING).is_file() else [])})
            os.replace(tmp_dir, out_dir)  # all files appear at once, never half-written
            metrics = _finite(result.metrics)
            message = ("done", "succeeded", None, metrics, files)
        except Cancelled as exc:
            message = ("done", "cancelled", str(exc) or "cancelled", None, [])
        except StrepError as exc:
            message = ("done", "failed", str(exc) or type(exc).__name__, None, [])
    except BaseException as exc:  # report anything, then exit non-zero
        traceback.print_exc()
        message = ("done", "failed", f"{type(exc).__name__}: {exc}", None, [])
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
    shutil.rmtree(tmp_dir, ignore_errors=True)
    with contextlib.suppress(OSError, ValueError):
        conn.send(message)
    conn.close()


# ---- upload validation -----------------------------------------------------------------------


def summarize(seq: Any) -> dict[str, Any]:
    return {
        "name": str(seq.name),
        "frames": len(seq),
        "dims": int(seq.dim),
        "points": int(seq.num_points),
        "unit": str(seq.unit),
        "has_ground_truth": bool(seq.poses is not None),
    }


def reader_loop(conn: multiprocessing.connection.Connection, plugins: list[str], nice: int = 0) -> None:
    """Serve read requests ``(path, selection, max_extract_bytes, extract_dir, max_points)`` until
    the pipe closes.

    Replies ``("ok", summary)`` or ``("error", error class name, message)``.
    """
    _watch_parent()
    _lower_priority(nice)
    _limit_threads(1)
    _import_plugins(plugins)
    from strep_core.errors import StrepError

    while True:
        try:
            path, selection, max_bytes, extract_dir, max_points = conn.recv()
        except (EOFError, OSError):
            return
        try:
            reply: tuple[Any, ...] = ("ok", summarize(load_source(path, selection, max_bytes, extract_dir, max_points)))
        except StrepError as exc:
            reply = ("error", type(exc).__name__, str(exc))
        except MemoryError:
            reply = ("error", "FormatError", "the file needs more memory to read than this service allows")
        except Exception as exc:  # a reader bug: report it as unreadable, keep serving
            traceback.print_exc()
            reply = ("error", "FormatError", f"the file could not be read ({type(exc).__name__}: {exc})")
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return
