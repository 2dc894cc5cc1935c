"""Code that runs in child processes (started with the ``spawn`` context).

* `run_job`: one process per job. Runs the job through the core's runner
  (`strep_core.runner.run_input`) on the upload's scene (read once, at upload: `job_input`),
  and once its frames are selected the scene is written to the job's folder
  (`app.services.scenes`) and a `app.rrd.RerunRecorder` opens ``recording.rrd``
  (recording id = job id); every event goes through the job's pipe. The result files are
  written into a temporary folder renamed into place, then a final `DoneMessage` is sent.
  The cancel flag is a ``multiprocessing.Event`` the core checks between iterations.
* `reader_loop`: a long-lived process that reads each upload once, within the service's
  limits, and writes it as a scene (`app.services.scenes`), so a reader that crashes or runs
  away never takes the service with it.

The spec and the messages are the models of `app.services.protocol`. The core (torch
included) is imported inside the functions, after the child has set its thread limits.
"""

from __future__ import annotations

import contextlib
import importlib
import json
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

from app.services.protocol import DoneMessage, EventMessage, JobSpec, ReadFailed, ReadOk, ReadRequest

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
            self.conn.send(EventMessage(event_kind=event.kind, data=event.model_dump_json(), emitted=time.time()))
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
    """An uploaded file as uploaded, read within the service's limits (bytes inflated, points;
    see `strep_core.io.limits`): by the upload reader, and by a job that gives reader options
    of its own. A ``.zip`` is extracted under ``extract_dir`` (a folder the service sweeps), if
    given. ``options`` go to the reader (`RunConfig.data`)."""
    from strep_core.io import load_sequence

    if extract_dir is not None:
        Path(extract_dir).mkdir(parents=True, exist_ok=True)
    limits: dict[str, Any] = {"max_extract_bytes": max_extract_bytes}
    if max_points is not None:
        limits["max_points"] = max_points
    return load_sequence(source, frames=selection, extract_dir=extract_dir, **limits, **(options or {}))


def job_input(spec: JobSpec, options: dict[str, Any]) -> Any:
    """The sequence a job registers (before its own frame selection): the upload's scene, read
    once at upload, as the command line reads any input; a bundled sample likewise; the file
    as uploaded only when the job gives reader options of its own."""
    from strep_core.runner import load_input

    if spec.scene is not None and not options:
        seq = load_input(spec.scene)
    elif spec.source.startswith("sample:"):
        seq = load_input(spec.source, options=options)
    else:
        seq = load_source(
            spec.source, spec.selection, spec.max_extract_bytes, spec.extract_dir, spec.max_points, options
        )
    if spec.sequence_name:  # an upload: its name, not its stored file's ("sequence")
        seq.name = spec.sequence_name
    return seq


class JobRecording:
    """The job's Rerun recording, a sink that must never fail the run.

    A recording is a by-product: failing to open or write one is logged in the job's log and
    the job runs on without it (the recorder then gets no more events); on exit the recorder
    is closed, and a recording that cannot be finished is dropped.
    """

    def __init__(self, path: Path, job_id: str, scene: Any, method: str) -> None:
        self.recorder: Any = None
        try:
            from app.rrd import RerunRecorder, disable_rerun_telemetry

            disable_rerun_telemetry()
            self.recorder = RerunRecorder(path, recording_id=job_id, sequence=scene, label=method)
        except Exception:
            print("recording.rrd cannot be written:", file=sys.stderr)
            traceback.print_exc()

    def emit(self, event: Any) -> None:
        if self.recorder is None:
            return
        try:
            self.recorder.emit(event)
        except Exception:
            traceback.print_exc()
            self._close(discard=True)

    def __enter__(self) -> JobRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.recorder is not None:  # normally closed already by the ResultEvent
            self._close(discard=bool(self.recorder.failed))

    def _close(self, *, discard: bool) -> None:
        recorder, self.recorder = self.recorder, None
        try:
            recorder.close(discard=discard)
        except Exception:
            traceback.print_exc()
            with contextlib.suppress(Exception):
                recorder.close(discard=True)
            Path(recorder.tmp_path).unlink(missing_ok=True)


def run_job(spec: JobSpec, conn: multiprocessing.connection.Connection, cancel: Any) -> None:
    """Entry point of a job's process; see the module docstring."""
    _watch_parent()
    _lower_priority(spec.nice)
    _limit_threads(spec.threads)
    _redirect_output(spec.log_path)
    tmp_dir = Path(spec.tmp_dir)
    message: DoneMessage
    try:
        _import_plugins(spec.plugins)
        from app.services.scenes import write_scene
        from strep_core.config import RunConfig
        from strep_core.errors import Cancelled, StrepError
        from strep_core.runner import run_input

        try:
            config = RunConfig.model_validate_json(spec.config)
            if config.threads is None:
                config = config.model_copy(update={"threads": spec.threads})

            def read(options: dict[str, Any]) -> Any:
                return job_input(spec, options)

            def job_sinks(scene: Any) -> list[Any]:
                """Once the frames are selected: the scene for the service, the recording."""
                write_scene(scene, spec.scene_path)
                if tmp_dir.exists():
                    shutil.rmtree(tmp_dir)
                tmp_dir.mkdir(parents=True)
                return [JobRecording(tmp_dir / RECORDING, spec.job_id, scene, config.method)]

            result = run_input(read, config, out_dir=tmp_dir, sink=PipeSink(conn), sinks=job_sinks, cancel=cancel)
            files = sorted({*result.files, *([RECORDING] if (tmp_dir / RECORDING).is_file() else [])})
            os.replace(tmp_dir, spec.out_dir)  # all files appear at once, never half-written
            resolved = json.loads(result.config.model_dump_json())
            message = DoneMessage(status="succeeded", metrics=_finite(result.metrics), files=files, config=resolved)
        except Cancelled as exc:
            message = DoneMessage(status="cancelled", error=str(exc) or "cancelled")
        except StrepError as exc:
            message = DoneMessage(status="failed", error=str(exc) or type(exc).__name__)
    except BaseException as exc:  # report anything, then exit non-zero
        traceback.print_exc()
        message = DoneMessage(status="failed", error=f"{type(exc).__name__}: {exc}")
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
    """Serve `ReadRequest` s until the pipe closes; each gets a `ReadOk` or a `ReadFailed`."""
    _watch_parent()
    _lower_priority(nice)
    _limit_threads(1)
    _import_plugins(plugins)
    from strep_core.errors import StrepError

    while True:
        try:
            request = ReadRequest.model_validate(conn.recv())
        except (EOFError, OSError):
            return
        reply: ReadOk | ReadFailed
        try:
            seq = load_source(
                request.path, request.selection, request.max_extract_bytes, request.extract_dir, request.max_points
            )
            if request.scene_path is not None:  # read once: jobs register this file
                from app.services.scenes import write_scene

                write_scene(seq, request.scene_path, exact=True)
            reply = ReadOk(summary=summarize(seq))
        except StrepError as exc:
            reply = ReadFailed(error_class=type(exc).__name__, message=str(exc))
        except MemoryError:
            reply = ReadFailed(
                error_class="FormatError", message="the file needs more memory to read than this service allows"
            )
        except Exception as exc:  # a reader bug: report it as unreadable, keep serving
            traceback.print_exc()
            reply = ReadFailed(
                error_class="FormatError", message=f"the file could not be read ({type(exc).__name__}: {exc})"
            )
        try:
            conn.send(reply)
        except (OSError, ValueError):
            return
