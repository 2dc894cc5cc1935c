"""Where jobs run: the executor seam behind `app.services.jobs.JobService`.

An executor starts one job and hands back two things the supervisor already knows how to
watch: a `multiprocessing` connection that carries the job's messages (`EventMessage` s, then
a `DoneMessage`: `app.services.protocol`) and a
`WorkerHandle` with the shape of a process (``sentinel``, ``exitcode``, ``terminate``,
``kill``, ...). Storage, live streams, cancel deadlines and reaping stay in the supervisor, the
same for every executor.

* ``local`` (default, `LocalExecutor`): one ``spawn`` process per job running
  `app.services.worker.run_job`, as before.
* ``ray`` (`RayExecutor`, ``STREP_EXECUTOR=ray``): one Ray actor per job, holding the job's
  CPUs (its threads) and one GPU when its config asks for ``device="cuda"``. The actor runs the
  same `run_job` in a thread and yields its messages from a streaming generator; a thread in
  the service writes them into a local pipe read by the supervisor. Cancel sets the actor's
  flag (checked between iterations, as locally); terminate and kill are `ray.kill`; an actor
  that dies (crash, node lost) ends its stream with an error and fails the job.

Ray workers read the job's input and write its results, recording and log at the service's
paths: every node must see the service's data directory at the same path (one host, or a
shared filesystem), and have strep-studio installed. Ray is an optional extra
(``pip install 'strep-studio[ray]'``) imported only here, and only when selected.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing.connection
import os
import signal
import threading
from multiprocessing.context import SpawnContext, SpawnProcess
from multiprocessing.synchronize import Event as MpEvent
from typing import Any, Protocol

from app.core.config import RAY_MISSING, Settings
from app.services.protocol import JobSpec, PidMessage
from app.services.sequences import describe_exit
from app.services.worker import run_job
from strep_core.errors import first_lines as _first_lines

log = logging.getLogger("strep.service")

RAY_UNKNOWN_EXIT = 1  # the exit code recorded for a Ray worker that died of something other than our kill


class ExecutorUnavailable(RuntimeError):
    """The selected executor cannot run here (Ray not installed, cluster unreachable)."""


class WorkerHandle(Protocol):
    """What the supervisor needs of a running job: a process, or something shaped like one."""

    pid: int | None

    @property
    def sentinel(self) -> Any:
        """Something `multiprocessing.connection.wait` accepts; ready once the worker has ended."""

    @property
    def exitcode(self) -> int | None:
        """``None`` while the worker runs; a negative code means ended by that signal."""

    def is_alive(self) -> bool: ...

    def cancel(self) -> None:
        """Set the job's cancel flag (the run stops between iterations)."""

    def terminate(self) -> None: ...

    def kill(self) -> None: ...

    def join(self, timeout: float | None = None) -> None: ...

    def failure_message(self) -> str:
        """Why the job failed when the worker ended without a ``done`` message."""

    def close(self) -> None:
        """Release what the handle holds; called once the worker has ended and its pipe is drained."""


class Executor(Protocol):
    name: str

    def start(self) -> None:
        """Prepare to launch jobs (connect to a cluster); called once before the first `launch`."""

    def launch(self, spec: JobSpec, device: str) -> tuple[WorkerHandle, multiprocessing.connection.Connection]:
        """Start ``run_job(spec, ...)``; the job's messages arrive on the returned connection."""

    def close(self) -> None:
        """Release the executor (after every worker has ended)."""


# ---- local worker processes ----------------------------------------------------------------------


class LocalWorker:
    """A job's ``spawn`` process and its `multiprocessing.Event` cancel flag."""

    def __init__(self, proc: SpawnProcess, cancel_flag: MpEvent) -> None:
        self.proc = proc
        self.cancel_flag = cancel_flag
        self.pid = proc.pid

    @property
    def sentinel(self) -> int:
        return self.proc.sentinel

    @property
    def exitcode(self) -> int | None:
        return self.proc.exitcode

    def is_alive(self) -> bool:
        return self.proc.is_alive()

    def cancel(self) -> None:
        self.cancel_flag.set()

    def terminate(self) -> None:
        self.proc.terminate()

    def kill(self) -> None:
        self.proc.kill()

    def join(self, timeout: float | None = None) -> None:
        self.proc.join(timeout)

    def failure_message(self) -> str:
        return f"the worker process {describe_exit(self.proc.exitcode)} before it reported a result"

    def close(self) -> None:
        pass


class LocalExecutor:
    """One ``spawn`` process per job on this machine (the default)."""

    name = "local"

    def __init__(self, ctx: SpawnContext) -> None:
        self.ctx = ctx

    def start(self) -> None:
        pass

    def launch(self, spec: JobSpec, device: str) -> tuple[LocalWorker, multiprocessing.connection.Connection]:
        parent, child = self.ctx.Pipe(duplex=False)
        cancel = self.ctx.Event()
        proc = self.ctx.Process(target=run_job, args=(spec, child, cancel), name=f"strep-{spec.job_id}", daemon=True)
        try:
            proc.start()
        except BaseException:
            parent.close()
            raise
        finally:
            child.close()
        return LocalWorker(proc, cancel), parent

    def close(self) -> None:
        pass


# ---- Ray -------------------------------------------------------------------------------------------


class JobActor:
    """The body of a job's Ray actor (made remote by `RayExecutor`; runs in a Ray worker process).

    Threaded (``max_concurrency=2``): `run` streams the job while `cancel` can still be called.
    The process is the job's alone (the actor is killed when the job ends), so `run_job` may
    redirect its output to the job's log and set its priority as in a local worker.
    """

    def __init__(self) -> None:
        self._cancel = threading.Event()

    def cancel(self) -> None:
        self._cancel.set()

    def run(self, spec: JobSpec, env: dict[str, str]) -> Any:
        """Yield a `PidMessage`, then every message `run_job` sends, the `DoneMessage` last.

        ``env``: the service's ``STREP_*`` variables (a worker of a cluster started elsewhere
        does not inherit them), set in this process before the job starts.
        """
        os.environ.update(env)
        yield PidMessage(pid=os.getpid())
        recv, send = multiprocessing.Pipe(duplex=False)
        thread = threading.Thread(target=run_job, args=(spec, send, self._cancel), name="strep-job", daemon=True)
        thread.start()
        try:
            while True:
                try:
                    message = recv.recv()
                except EOFError:  # run_job closes its end after its last message
                    break
                yield message
        finally:
            thread.join(timeout=5)
            recv.close()


def forwarded_env() -> dict[str, str]:
    """The service's ``STREP_*`` environment for a job's Ray worker; never the API token."""
    return {k: v for k, v in os.environ.items() if k.startswith("STREP_") and k != "STREP_API_TOKEN"}


def ray_resources(device: str, threads: int) -> dict[str, float]:
    """The Ray resource request of a job: its CPU threads, and one GPU for ``device="cuda"``."""
    return {"num_cpus": float(threads), "num_gpus": 1.0 if device == "cuda" else 0.0}


class RayWorker:
    """A job running in a Ray actor, seen through a process-like handle.

    A relay thread iterates the actor's stream and writes each message into ``conn`` (the
    supervisor's pipe). When the stream ends (normally, or with an error when the actor died
    or was killed) the thread records the exit code, closes the pipe, kills the actor (it holds
    the job's CPUs/GPU) and closes ``_sentinel_w``, which makes `sentinel` ready.
    """

    def __init__(self, actor: Any, stream: Any, conn: multiprocessing.connection.Connection, job_id: str) -> None:
        self.actor = actor
        self.stream = stream
        self.conn = conn
        self.job_id = job_id
        self.pid: int | None = None
        self._exitcode: int | None = None
        self._reason = "the Ray worker ended before it reported a result"
        self._killed_by: int | None = None  # the signal our terminate()/kill() stands for
        self._sentinel_r, self._sentinel_w = os.pipe()
        self._thread = threading.Thread(target=self._relay, name=f"strep-ray-{job_id}", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        import ray

        code: int = 0
        try:
            for ref in self.stream:
                message = ray.get(ref)
                if isinstance(message, PidMessage):
                    self.pid = message.pid
                try:
                    self.conn.send(message)
                except (OSError, ValueError):  # the supervisor closed its end: the service is stopping
                    code = -self._killed_by if self._killed_by is not None else 0
                    break
        except ray.exceptions.RayActorError as exc:
            if self._killed_by is not None:
                code = -self._killed_by
                self._reason = f"the Ray worker {describe_exit(code)} (ray.kill) before it reported a result"
            else:
                code = RAY_UNKNOWN_EXIT
                self._reason = f"the Ray worker died before it reported a result: {_first_lines(str(exc))}"
        except Exception as exc:  # the stream itself failed (a bug in the actor, a Ray error)
            log.exception("the Ray stream of job %s failed", self.job_id)
            code = RAY_UNKNOWN_EXIT
            self._reason = f"the Ray task failed: {type(exc).__name__}: {_first_lines(str(exc))}"
        finally:
            self._exitcode = code
            with contextlib.suppress(OSError):
                self.conn.close()
            with contextlib.suppress(Exception):
                ray.kill(self.actor, no_restart=True)
            os.close(self._sentinel_w)

    @property
    def sentinel(self) -> int:
        return self._sentinel_r

    @property
    def exitcode(self) -> int | None:
        return self._exitcode

    def is_alive(self) -> bool:
        return self._exitcode is None

    def cancel(self) -> None:
        with contextlib.suppress(Exception):
            self.actor.cancel.remote()

    def _kill(self, sig: int) -> None:
        import ray

        if self._exitcode is not None:
            return
        if self._killed_by is None:
            self._killed_by = int(sig)
        with contextlib.suppress(Exception):
            ray.kill(self.actor, no_restart=True)

    def terminate(self) -> None:
        """End the actor at once (`ray.kill`); recorded as ``-SIGTERM`` like a terminated process."""
        self._kill(signal.SIGTERM)

    def kill(self) -> None:
        self._kill(signal.SIGKILL)

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def failure_message(self) -> str:
        return self._reason

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self._sentinel_r)


class RayExecutor:
    """One Ray actor per job, on the cluster at ``settings.ray_address``.

    `start` connects (``auto``: an existing cluster, failing if none; ``local``: a new local
    runtime with ``ray_num_cpus`` CPUs; anything else: that cluster address). When Ray is
    already initialised in this process (tests, an embedding program) that connection is used
    and left open at `close`.
    """

    name = "ray"

    def __init__(self, settings: Settings, ctx: SpawnContext) -> None:
        try:
            import ray  # noqa: F401
        except ImportError as exc:
            raise ExecutorUnavailable(RAY_MISSING) from exc
        self.settings = settings
        self.ctx = ctx
        self._actor_class: Any = None
        self._owns_ray = False

    def start(self) -> None:
        import ray

        if ray.is_initialized():
            log.info("jobs run on the Ray cluster this process is already connected to")
        else:
            address = self.settings.ray_address
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if address == "local" and self.settings.ray_num_cpus is not None:
                kwargs["num_cpus"] = self.settings.ray_num_cpus
            previous = signal.getsignal(signal.SIGTERM) if _main_thread() else None
            try:
                ray.init(address=address, **kwargs)
            except Exception as exc:
                raise ExecutorUnavailable(f"cannot connect to Ray at {address!r}: {exc}") from exc
            finally:
                if previous is not None:  # ray.init replaces the SIGTERM handler (uvicorn's)
                    signal.signal(signal.SIGTERM, previous)
            self._owns_ray = True
            log.info("jobs run on Ray (%s): %s", address, ray.cluster_resources())
        self._actor_class = ray.remote(max_concurrency=2)(JobActor)  # type: ignore[call-overload]  # valid for classes

    def launch(self, spec: JobSpec, device: str) -> tuple[RayWorker, multiprocessing.connection.Connection]:
        import ray

        resources = ray_resources(device, spec.threads)
        self._warn_if_infeasible(resources)
        actor = self._actor_class.options(**resources).remote()
        try:
            stream = actor.run.remote(spec, forwarded_env())
            parent, child = self.ctx.Pipe(duplex=False)
        except BaseException:
            ray.kill(actor, no_restart=True)
            raise
        return RayWorker(actor, stream, child, spec.job_id), parent

    def _warn_if_infeasible(self, resources: dict[str, float]) -> None:
        """Log when no node is as large as the request: Ray then waits for one (an autoscaler may add it)."""
        import ray

        with contextlib.suppress(Exception):
            for node in ray.nodes():
                have = node.get("Resources", {}) if node.get("Alive") else {}
                if have.get("CPU", 0) >= resources["num_cpus"] and have.get("GPU", 0) >= resources["num_gpus"]:
                    return
            log.warning("no Ray node has %s: the job waits until one joins the cluster", resources)

    def close(self) -> None:
        if self._owns_ray:
            import ray

            ray.shutdown()
            self._owns_ray = False


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def make_executor(settings: Settings, ctx: SpawnContext) -> Executor:
    """The executor ``settings.executor`` names."""
    if settings.executor == "ray":
        return RayExecutor(settings, ctx)
    return LocalExecutor(ctx)
