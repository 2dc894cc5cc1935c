"""Job execution: a FIFO queue, at most N worker processes, one supervisor thread.

Process model: one ``spawn`` process per job (`app.services.worker.run_job`), so a crash or
a kill ends only that job; with ``executor="ray"`` one Ray actor per job instead, behind the
same process-like handle and pipe (`app.services.executors`). Each worker has its own pipe
(no lock shared between processes, so a worker killed mid-write cannot wedge the others); the
end of its pipe tells the supervisor the worker is gone, after every message it sent.

The supervisor thread owns the running workers. It waits on their pipes, their process
sentinels and a wake-up pipe; it stores each round of events in one SQLite transaction,
then publishes them to live subscribers; it starts queued jobs while fewer than
``max_concurrent_jobs`` workers are alive; it enforces cancel deadlines. API threads only
write the store (new jobs, cancelling queued ones) and wake it.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import queue
import shutil
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.context import SpawnContext
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from app.core.config import Settings
from app.services.broadcast import Broadcaster
from app.services.executors import WorkerHandle, make_executor
from app.services.protocol import DoneMessage, EventMessage, JobSpec, PidMessage, parse_message
from app.services.scenes import SCENE
from app.services.sequences import SequenceService, new_id
from app.store import EventIn, StatusChange, Store, StoredEvent, now_iso
from strep_core.config import RunConfig

log = logging.getLogger("strep.service")

KILL_AFTER_TERMINATE = 2.0  # seconds between SIGTERM and SIGKILL
# a worker that closed its pipe but does not exit is killed after this; 30 s, not 10: on 2 cores
# under four processes a strep worker's clean exit (torch's teardown) took over 10 s and was killed
REAP_TIMEOUT = 30.0
MAX_MESSAGES_PER_ROUND = 500  # per worker, so one chatty worker cannot starve the others
MEMORY_POLL = 0.2  # seconds between two looks at the workers' resident memory (with a budget)


def resident_bytes(pid: int | None) -> int | None:
    """The resident memory of process ``pid`` (bytes, from /proc), or None where it cannot be read."""
    if pid is None:
        return None
    try:
        pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE")


@dataclass
class _Worker:
    job_id: str
    proc: WorkerHandle  # a local process, or a Ray actor seen as one
    conn: multiprocessing.connection.Connection
    done: bool = False
    eof: bool = False
    cancel_deadline: float | None = None
    kill_deadline: float | None = None
    reap_deadline: float | None = None
    terminated: bool = False
    over_budget: str | None = None  # why it was killed, when it held more memory than the job's budget


class JobService:
    """Queues, runs, cancels and supervises jobs. Start with `start`, stop with `close`."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        broadcaster: Broadcaster,
        sequences: SequenceService,
        ctx: SpawnContext,
    ) -> None:
        self.settings = settings
        self.store = store
        self.broadcaster = broadcaster
        self.sequences = sequences
        self.ctx = ctx
        self.executor = make_executor(settings, ctx)
        self._workers: dict[str, _Worker] = {}
        self._commands: queue.SimpleQueue[tuple[str, str]] = queue.SimpleQueue()
        self._wake_r, self._wake_w = ctx.Pipe(duplex=False)
        self._wake_lock = threading.Lock()
        self._wake_pending = False
        self._stop = threading.Event()
        self._start_pending = True
        self._thread: threading.Thread | None = None

    # ---- folders ---------------------------------------------------------------------------
    @property
    def tmp_results(self) -> Path:
        return self.settings.results_dir / ".tmp"

    def result_dir(self, job_id: str) -> Path:
        return self.settings.results_dir / job_id

    def scene_path(self, job_id: str) -> Path:
        """The frames the job registers, written by its worker (`app.services.scenes`)."""
        return self.settings.data_dir / "jobs" / job_id / SCENE

    # ---- life cycle ------------------------------------------------------------------------
    def start(self) -> None:
        """Recover from the previous run, then start the supervisor thread.

        Jobs the store says are ``running`` belonged to a service that died: they become
        ``interrupted`` (their partial outputs are removed). ``queued`` jobs stay queued and
        start in their original order.
        """
        shutil.rmtree(self.tmp_results, ignore_errors=True)
        self.tmp_results.mkdir(parents=True, exist_ok=True)
        self.settings.logs_dir.mkdir(parents=True, exist_ok=True)
        changes = [
            StatusChange(job["id"], ("running",), "interrupted", "the service stopped while this job was running")
            for job in self.store.jobs_with_status("running")
        ]
        if changes:
            log.warning("marking %d job(s) interrupted", len(changes))
            self.store.apply(changes)
        self.executor.start()
        self._thread = threading.Thread(target=self._run, name="strep-supervisor", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the supervisor; stop running workers and mark their jobs ``interrupted``."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout=30)
        workers = list(self._workers.values())
        pending: list[EventIn | StatusChange] = []
        for w in workers:  # what finished workers said last still counts
            if not w.eof:
                self._read(w, pending)
        if pending:
            self._store_and_publish(pending)
        for w in workers:
            w.proc.cancel()
            if w.proc.is_alive():
                w.proc.terminate()
        deadline = time.monotonic() + KILL_AFTER_TERMINATE
        for w in workers:
            w.proc.join(timeout=max(0.0, deadline - time.monotonic()))
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join(timeout=5)
            w.conn.close()
            w.proc.close()
            shutil.rmtree(self.tmp_results / w.job_id, ignore_errors=True)
        changes = [
            StatusChange(
                w.job_id,
                ("running",),
                "interrupted",
                "the service shut down while this job was running",
                (("exit_code", w.proc.exitcode),),
            )
            for w in workers
        ]
        if changes:
            self._store_and_publish(changes)
        self._workers.clear()
        self.executor.close()
        self._wake_r.close()
        self._wake_w.close()

    # ---- called from API threads ---------------------------------------------------------
    def submit(
        self, sequence_id: str, configs: list[RunConfig], *, comparison_methods: list[str] | None = None
    ) -> tuple[list[str], str | None]:
        """Queue one job per config (a comparison when ``comparison_methods`` is given)."""
        created = now_iso()
        comparison: dict[str, Any] | None = None
        if comparison_methods is not None:
            comparison = {
                "id": new_id("cmp"),
                "sequence_id": sequence_id,
                "methods": comparison_methods,
                "created_at": created,
            }
        comparison_id: str | None = comparison["id"] if comparison else None
        jobs: list[dict[str, Any]] = [
            {
                "id": new_id("job"),
                "sequence_id": sequence_id,
                "comparison_id": comparison_id,
                "method": cfg.method,
                "config": cfg.model_dump_json(exclude_unset=True),  # the request: resolved by the run
                "created_at": created,
            }
            for cfg in configs
        ]
        events = self.store.insert_jobs(jobs, comparison)
        self.broadcaster.publish(events)
        self._start_pending = True
        self._wake()
        return [str(j["id"]) for j in jobs], comparison_id

    def cancel(self, job_id: str) -> dict[str, Any] | None:
        """Cancel a job: a queued one at once, a running one through its flag (then SIGTERM).

        Returns the job as it is after the request (``None`` if unknown).
        """
        job = self.store.get_job(job_id)
        if job is None:
            return None
        if job["status"] == "queued":
            stored = self.store.apply(
                [
                    StatusChange(
                        job_id, ("queued",), "cancelled", "cancelled before it started", (("cancel_requested", True),)
                    )
                ]
            )
            self.broadcaster.publish(stored)
            job = self.store.get_job(job_id)
            assert job is not None
        if job["status"] == "running":
            if not job["cancel_requested"]:
                self.store.set_job_fields(job_id, cancel_requested=True)
            self._commands.put(("cancel", job_id))
            self._wake()
            job = self.store.get_job(job_id)
        return job

    def worker_pid(self, job_id: str) -> int | None:
        w = self._workers.get(job_id)
        return w.proc.pid if w is not None else None

    def counts(self) -> tuple[int, int]:
        """``(running, queued)`` jobs."""
        _, running = self.store.list_jobs(status="running", limit=0)
        _, queued = self.store.list_jobs(status="queued", limit=0)
        return running, queued

    def _wake(self) -> None:
        with self._wake_lock:
            if self._wake_pending:
                return
            self._wake_pending = True
            with contextlib.suppress(OSError):
                self._wake_w.send_bytes(b"w")

    # ---- the supervisor thread -----------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._round()
            except Exception:  # keep supervising whatever happens
                log.exception("supervisor round failed")
                self._start_pending = True
                time.sleep(0.5)

    def _round(self) -> None:
        if self._start_pending:
            self._start_pending = False
            self._start_queued()
        waitables: list[Any] = [self._wake_r]
        for w in self._workers.values():
            if not w.eof:
                waitables.append(w.conn)
            if w.proc.exitcode is None:
                waitables.append(w.proc.sentinel)
        ready = multiprocessing.connection.wait(waitables, timeout=self._timeout())
        if self._wake_r in ready:
            with self._wake_lock:
                while self._wake_r.poll():
                    self._wake_r.recv_bytes()
                self._wake_pending = False
        self._handle_commands()
        items: list[EventIn | StatusChange] = []
        for w in list(self._workers.values()):
            if not w.eof and w.conn in ready:
                self._read(w, items)
        if items:
            self._store_and_publish(items)
        self._enforce_memory()
        self._reap()
        self._enforce_deadlines()

    def _timeout(self) -> float:
        now = time.monotonic()
        deadlines = [
            d for w in self._workers.values() for d in (w.cancel_deadline, w.kill_deadline, w.reap_deadline) if d
        ]
        poll = MEMORY_POLL if self._workers and self.settings.job_memory_mib is not None else 1.0
        return max(0.01, min([poll, *(d - now for d in deadlines)]))

    def _read(self, w: _Worker, items: list[EventIn | StatusChange]) -> None:
        try:
            for _ in range(MAX_MESSAGES_PER_ROUND):
                if not w.conn.poll():
                    return
                msg = parse_message(w.conn.recv())
                if isinstance(msg, EventMessage):
                    items.append(EventIn(w.job_id, msg.event_kind, msg.data, msg.emitted))
                elif isinstance(msg, DoneMessage):
                    w.done = True
                    fields: tuple[tuple[str, Any], ...] = (("metrics", msg.metrics), ("files", msg.files))
                    if msg.config is not None:  # the request becomes what ran (its config.json)
                        fields += (("config", self._public_config(w.job_id, msg.config)),)
                    items.append(StatusChange(w.job_id, ("running",), msg.status, msg.error, fields))
                elif isinstance(msg, PidMessage):  # a Ray worker's process, known once its actor has started
                    self.store.set_job_fields(w.job_id, pid=msg.pid)
        except (EOFError, OSError):
            w.eof = True
        except Exception:  # an unreadable message: treat the worker as broken
            log.exception("bad message from the worker of %s", w.job_id)
            w.eof = True
            if w.proc.is_alive():
                w.proc.kill()

    def _public_config(self, job_id: str, resolved: dict[str, Any]) -> dict[str, Any]:
        """The resolved config as the API shows it: ``from_model`` as requested (``job:<id>``),
        not the server path the worker read."""
        job = self.store.get_job(job_id)
        requested = (job or {}).get("config", {}).get("from_model")
        return {**resolved, "from_model": requested} if resolved.get("from_model") else resolved

    def _store_and_publish(self, items: Sequence[EventIn | StatusChange]) -> list[StoredEvent]:
        stored = self.store.apply(items)
        self.broadcaster.publish(stored)
        return stored

    def _handle_commands(self) -> None:
        while True:
            try:
                command, job_id = self._commands.get_nowait()
            except queue.Empty:
                return
            w = self._workers.get(job_id)
            if command == "cancel" and w is not None and w.cancel_deadline is None and not w.done:
                w.proc.cancel()
                w.cancel_deadline = time.monotonic() + self.settings.cancel_grace_seconds

    def _enforce_memory(self) -> None:
        """Kill a worker holding more than ``job_memory_mib``; its job fails saying so."""
        budget = self.settings.job_memory_mib
        if budget is None or self.executor.name != "local":  # a Ray worker's pid may be another machine's
            return
        for w in self._workers.values():
            if w.over_budget is not None or w.done or w.proc.exitcode is not None:
                continue
            rss = resident_bytes(w.proc.pid)
            if rss is not None and rss > budget * 2**20:
                w.over_budget = (
                    f"the job held {rss / 2**20:.0f} MiB, more than its memory budget of {budget} MiB "
                    "(STREP_JOB_MEMORY_MIB); give it fewer frames or points, or raise the budget"
                )
                log.warning("job %s: %s; killing its worker", w.job_id, w.over_budget)
                w.proc.kill()

    def _enforce_deadlines(self) -> None:
        now = time.monotonic()
        for w in self._workers.values():
            if w.proc.exitcode is not None:
                # exited, yet its pipe is still open (a descendant holds it): stop waiting after a while
                if not w.eof and w.reap_deadline is None:
                    w.reap_deadline = now + REAP_TIMEOUT
                elif not w.eof and w.reap_deadline is not None and now >= w.reap_deadline:
                    w.eof = True
                continue
            if w.cancel_deadline is not None and now >= w.cancel_deadline and not w.terminated:
                log.warning(
                    "job %s did not stop within %.1f s of its cancel; terminating",
                    w.job_id,
                    self.settings.cancel_grace_seconds,
                )
                w.proc.terminate()
                w.terminated = True
                w.kill_deadline = now + KILL_AFTER_TERMINATE
            elif w.kill_deadline is not None and now >= w.kill_deadline:
                w.proc.kill()
                w.kill_deadline = None
            elif w.eof and w.reap_deadline is None:
                w.reap_deadline = now + REAP_TIMEOUT
            elif w.reap_deadline is not None and now >= w.reap_deadline:
                log.warning("the worker of job %s closed its pipe but did not exit; killing it", w.job_id)
                w.proc.kill()
                w.reap_deadline = None

    def _reap(self) -> None:
        """Finish jobs whose worker has exited and whose pipe is drained."""
        for w in list(self._workers.values()):
            if not w.eof or w.proc.exitcode is None:
                continue
            w.proc.join(timeout=0)
            code = w.proc.exitcode
            w.conn.close()
            w.proc.close()
            del self._workers[w.job_id]
            self._start_pending = True
            shutil.rmtree(self.tmp_results / w.job_id, ignore_errors=True)
            if w.done:
                self.store.set_job_fields(w.job_id, exit_code=code)
                continue
            if w.cancel_deadline is not None:
                how = f" (the worker did not stop within {self.settings.cancel_grace_seconds:g} s and was terminated)"
                change = StatusChange(
                    w.job_id,
                    ("running",),
                    "cancelled",
                    "cancelled" + (how if w.terminated else ""),
                    (("exit_code", code),),
                )
            else:
                change = StatusChange(
                    w.job_id,
                    ("running",),
                    "failed",
                    w.over_budget or w.proc.failure_message(),
                    (("exit_code", code),),
                )
            self._store_and_publish([change])

    def _start_queued(self) -> None:
        free = self.settings.max_concurrent_jobs - len(self._workers)
        while free > 0 and not self._stop.is_set():
            queued = self.store.next_queued(free)
            if not queued:
                return
            for job in queued:
                if self._launch(job):
                    free -= 1

    def _launch(self, job: dict[str, Any]) -> bool:
        job_id = job["id"]
        source = self.sequences.source_of(job["sequence_id"])
        if source is None:
            self._store_and_publish(
                [StatusChange(job_id, ("queued",), "failed", f"sequence {job['sequence_id']} no longer exists")]
            )
            return False
        path, selection, scene = source
        try:
            config = RunConfig.model_validate(job["config"])
        except ValidationError as exc:  # queued by an older version whose config no longer validates
            self._store_and_publish(
                [StatusChange(job_id, ("queued",), "failed", f"its configuration is no longer valid: {exc}")]
            )
            return False
        if config.from_model and config.from_model.startswith("job:"):
            model = self.result_dir(config.from_model[4:]) / "model.pt"
            config = config.model_copy(update={"from_model": str(model)})
        if not self._store_and_publish([StatusChange(job_id, ("queued",), "running")]):
            return False  # cancelled meanwhile
        spec = JobSpec(
            job_id=job_id,
            source=str(path),
            selection=selection,
            scene=scene,
            sequence_name=self.sequences.name_of(job["sequence_id"]),  # not "sequence", the stored name
            config=config.model_dump_json(exclude_unset=True),
            scene_path=str(self.scene_path(job_id)),
            tmp_dir=str(self.tmp_results / job_id),
            out_dir=str(self.result_dir(job_id)),
            log_path=str(self.settings.logs_dir / f"{job_id}.log"),
            threads=self.settings.threads_per_job(),
            nice=self.settings.worker_nice,
            max_extract_bytes=self.settings.max_inflated_bytes,
            max_points=self.settings.max_points,
            # a worker killed mid-extraction leaves it in its tmp_dir, removed when the job ends
            extract_dir=str(self.tmp_results / job_id),
            plugins=list(self.settings.plugins),
        )
        try:
            proc, conn = self.executor.launch(spec, config.device)
        except Exception as exc:
            log.exception("cannot start the worker of %s", job_id)
            self._store_and_publish(
                [StatusChange(job_id, ("running",), "failed", f"cannot start a worker process: {exc}")]
            )
            return False
        self._workers[job_id] = _Worker(job_id=job_id, proc=proc, conn=conn)
        if proc.pid is not None:
            self.store.set_job_fields(job_id, pid=proc.pid)
        log.info("job %s (%s) started (%s executor, process %s)", job_id, job["method"], self.executor.name, proc.pid)
        return True
