"""Sequences: uploads (validated by reading them in a separate process) and bundled samples.

Uploads are read one at a time by one reader process, fed by a thread of its own: a request
waiting for the reader holds no thread of the server's pool, so health and read endpoints
never wait on a reader. At most ``max_pending_uploads`` uploads are received, queued or read
at once (`SequenceService.reserve_upload`); one more is refused at once with 429.
"""

from __future__ import annotations

import importlib.util
import logging
import multiprocessing
import multiprocessing.connection
import re
import secrets
import shutil
import signal
import threading
import zipfile
from concurrent.futures import Future, ThreadPoolExecutor
from multiprocessing.context import SpawnContext, SpawnProcess
from pathlib import Path
from typing import Any

from app.core.config import Settings
from app.services.protocol import ReadOk, ReadRequest, parse_read_reply
from app.services.scenes import UPLOAD_SCENE
from app.services.uploads import ReceivedUpload, UploadError
from app.services.worker import reader_loop
from app.store import Store, now_iso
from strep_core import errors as core_errors
from strep_core import sequence as core_sequence
from strep_core.errors import ConfigError, FormatError, SequenceError, StrepError
from strep_core.sequence import FrameSelection

log = logging.getLogger("strep.service")

SAMPLE_PREFIX = "sample:"
_EXTRACTED = re.compile(r"[^\s'\"]*strep-zip-[^/\s]+/")  # the temporary folder a .zip is extracted into


def new_id(prefix: str) -> str:
    return f"{prefix}_{secrets.token_hex(8)}"


def describe_exit(code: int | None) -> str:
    """Why a process ended, in words: ``killed by signal SIGKILL`` or ``exited with code 1``."""
    if code is None:
        return "is still running"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = str(-code)
        return f"was killed by signal {name}"
    return f"exited with code {code}"


class ReaderProcess:
    """A long-lived child process that reads uploads (one at a time) to validate them.

    A reader that crashes, hangs past the timeout or runs out of memory ends only this
    process; it is started again for the next upload.
    """

    def __init__(
        self, ctx: SpawnContext, *, plugins: list[str], timeout: float, extract_dir: Path, nice: int = 0
    ) -> None:
        self.ctx = ctx
        self.extract_dir = extract_dir  # where archives are extracted; emptied when the reader is killed
        self.plugins = plugins
        self.nice = nice
        self.timeout = timeout
        self._lock = threading.Lock()
        self._proc: SpawnProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None

    def _ensure(self) -> multiprocessing.connection.Connection:
        if self._proc is not None and self._proc.is_alive() and self._conn is not None:
            return self._conn
        self._stop()
        parent, child = self.ctx.Pipe()
        proc = self.ctx.Process(
            target=reader_loop, args=(child, self.plugins, self.nice), name="strep-reader", daemon=True
        )
        proc.start()
        child.close()
        self._proc, self._conn = proc, parent
        return parent

    def _stop(self) -> int | None:
        code = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            self._proc.join(timeout=2)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join(timeout=5)
            code = self._proc.exitcode
            self._proc = None
            # a reader killed mid-extraction leaves its folder behind
            for entry in self.extract_dir.glob("strep-zip-*"):
                shutil.rmtree(entry, ignore_errors=True)
        return code

    def read(
        self,
        path: Path,
        selection: str | None,
        max_extract_bytes: int,
        max_points: int | None = None,
        scene_path: Path | None = None,
    ) -> dict[str, Any]:
        """Read ``path`` as a sequence (written to ``scene_path`` if given); returns its summary
        or raises the reader's `StrepError`."""
        with self._lock:
            conn = self._ensure()
            request = ReadRequest(
                path=str(path),
                selection=selection,
                max_extract_bytes=max_extract_bytes,
                extract_dir=str(self.extract_dir),
                max_points=max_points,
                scene_path=None if scene_path is None else str(scene_path),
            )
            conn.send(request)
            if not conn.poll(self.timeout):
                assert self._proc is not None
                self._proc.kill()
                self._stop()
                raise FormatError(f"reading the file took longer than {self.timeout:g} s; it was refused")
            try:
                reply = parse_read_reply(conn.recv())
            except (EOFError, OSError):
                code = self._stop()
                raise FormatError(f"the file could not be read: the reader process {describe_exit(code)}") from None
        if isinstance(reply, ReadOk):
            return dict(reply.summary)
        cls = getattr(core_errors, reply.error_class, None) or getattr(core_sequence, reply.error_class, None)
        if not (isinstance(cls, type) and issubclass(cls, StrepError)):
            cls = FormatError
        raise cls(reply.message)

    def close(self) -> None:
        with self._lock:
            self._stop()


RETRY_AFTER_SECONDS = 5  # the Retry-After of a 429 for an upload while the queue is full


class UploadSlot:
    """One of the ``max_pending_uploads`` places of an upload (receiving, queued or being read);
    released once, by whoever holds it last."""

    def __init__(self, owner: SequenceService) -> None:
        self._owner = owner
        self._released = False

    def release(self) -> None:
        if not self._released:
            self._released = True
            self._owner._release_slot()


class SequenceService:
    """Uploaded sequences (rows in the store, files under ``uploads/``) and bundled samples."""

    def __init__(self, settings: Settings, store: Store, ctx: SpawnContext) -> None:
        self.settings = settings
        self.store = store
        self.reader = ReaderProcess(
            ctx,
            plugins=settings.plugins,
            timeout=settings.read_timeout_seconds,
            extract_dir=self.extract_dir / "reader",
            nice=settings.worker_nice,
        )
        self._samples: dict[str, dict[str, Any]] | None = None
        self._samples_lock = threading.Lock()
        self._slots_lock = threading.Lock()
        self._slots_taken = 0
        self._reads = ThreadPoolExecutor(max_workers=1, thread_name_prefix="strep-upload-read")

    @property
    def tmp_dir(self) -> Path:
        """Uploads being received: removed at start-up."""
        return self.settings.uploads_dir / ".tmp"

    @property
    def extract_dir(self) -> Path:
        """Archives being read: by the reader process in ``reader/``, by the service in ``service/``;
        removed at start-up."""
        return self.settings.uploads_dir / ".extract"

    # ---- samples ---------------------------------------------------------------------------
    def samples(self) -> dict[str, dict[str, Any]]:
        """Bundled samples by id (``sample:NAME``); empty while `strep_core.samples` is absent."""
        with self._samples_lock:
            if self._samples is None:
                self._samples = self._load_samples()
            return self._samples

    @staticmethod
    def _load_samples() -> dict[str, dict[str, Any]]:
        if importlib.util.find_spec("strep_core.samples") is None:
            return {}
        from strep_core import samples

        out: dict[str, dict[str, Any]] = {}
        for info in samples.list_samples():
            get = info.get if isinstance(info, dict) else lambda k, d=None, i=info: getattr(i, k, d)
            name = str(get("name"))
            out[SAMPLE_PREFIX + name] = {
                "id": SAMPLE_PREFIX + name,
                "name": name,
                "source": "sample",
                "frames": int(get("frames", 0) or 0),
                "dims": int(get("dims", 0) or 0),
                "points": int(get("points", 0) or 0),
                "unit": get("unit"),
                "has_ground_truth": get("has_ground_truth", _sample_has_poses(samples, name)),
                "description": get("description"),
            }
        return out

    # ---- queries ---------------------------------------------------------------------------
    def list(self) -> list[dict[str, Any]]:
        uploaded = [_public(row) for row in self.store.list_sequences()]
        return [*self.samples().values(), *uploaded]

    def get(self, sequence_id: str) -> dict[str, Any] | None:
        if sequence_id.startswith(SAMPLE_PREFIX):
            return self.samples().get(sequence_id)
        row = self.store.get_sequence(sequence_id)
        return _public(row) if row else None

    def source_of(self, sequence_id: str) -> tuple[str, str | None, str | None] | None:
        """``(source, selection, scene)`` for a job's worker: ``sample:NAME``, or the stored
        file's path, its selection and the scene it was read into (None for uploads stored
        before scenes were)."""
        if sequence_id.startswith(SAMPLE_PREFIX):
            return (sequence_id, None, None) if sequence_id in self.samples() else None
        row = self.store.get_sequence(sequence_id)
        if row is None:
            return None
        stored = self.settings.data_dir / row["path"]
        scene = stored.parent / UPLOAD_SCENE
        return str(stored), row["selection"], str(scene) if scene.is_file() else None

    def name_of(self, sequence_id: str) -> str | None:
        """An uploaded sequence's name (the uploaded file's, unless given): the worker names the
        sequence it reads so (the stored copy is ``sequence.<ext>``); None for samples."""
        if sequence_id.startswith(SAMPLE_PREFIX):
            return None
        row = self.store.get_sequence(sequence_id)
        return None if row is None else str(row["name"])

    # ---- uploads ---------------------------------------------------------------------------
    @property
    def pending_uploads(self) -> int:
        """Uploads being received, waiting for the reader or being read."""
        with self._slots_lock:
            return self._slots_taken

    def reserve_upload(self) -> UploadSlot:
        """A place for one more upload, before its body is read; `UploadError` 429 when all
        ``max_pending_uploads`` are taken."""
        limit = self.settings.max_pending_uploads
        with self._slots_lock:
            if self._slots_taken >= limit:
                raise UploadError(
                    429,
                    f"too many uploads at once: {limit} are being received or read; retry later",
                    {"Retry-After": str(RETRY_AFTER_SECONDS)},
                )
            self._slots_taken += 1
        return UploadSlot(self)

    def _release_slot(self) -> None:
        with self._slots_lock:
            self._slots_taken -= 1

    def submit_upload(self, upload: ReceivedUpload, slot: UploadSlot) -> Future[dict[str, Any]]:
        """Queue ``upload`` for the reader (`add_upload` on the reader's thread). The upload's
        temporary file and its slot are the queue's from now on: both are let go when the read
        ends, whether or not anyone still waits for it."""

        def read() -> dict[str, Any]:
            try:
                return self.add_upload(upload)
            finally:
                upload.path.unlink(missing_ok=True)
                slot.release()

        try:
            return self._reads.submit(read)
        except RuntimeError:  # shutting down
            upload.path.unlink(missing_ok=True)
            slot.release()
            raise

    def add_upload(self, upload: ReceivedUpload) -> dict[str, Any]:
        """Validate an upload by reading it, then keep it: rename into place, insert its row.

        Raises `StrepError` (bad content or options); the temporary file is the caller's.
        """
        selection = upload.fields.get("frames") or None
        if selection is not None:
            try:
                selection = str(FrameSelection.parse(selection))
            except SequenceError as exc:
                raise ConfigError(f"frames: {exc}") from exc
        name = (upload.fields.get("name") or "").strip()
        if len(name) > 200 or not all(ch.isprintable() for ch in name):
            raise ConfigError("name: at most 200 printable characters")
        seq_id = new_id("seq")
        folder = self.settings.uploads_dir / seq_id
        folder.mkdir(parents=True)
        try:  # read once, into the scene jobs register
            summary = self.reader.read(
                upload.path,
                selection,
                self.settings.max_inflated_bytes,
                self.settings.max_points,
                folder / UPLOAD_SCENE,
            )
        except BaseException as exc:
            shutil.rmtree(folder, ignore_errors=True)
            if isinstance(exc, StrepError):
                raise type(exc)(_clean(str(exc), upload.path, upload.filename)) from None
            raise
        stored = folder / f"sequence{upload.suffix}"
        try:
            upload.path.replace(stored)
            row = {
                "id": seq_id,
                "name": name or _default_name(upload.filename, upload.suffix, summary),
                "filename": upload.filename,
                "path": str(stored.relative_to(self.settings.data_dir)),
                "format": upload.format,
                "selection": selection,
                "frames": summary["frames"],
                "dims": summary["dims"],
                "points": summary["points"],
                "unit": summary["unit"],
                "has_ground_truth": int(summary["has_ground_truth"]),
                "size_bytes": upload.size,
                "created_at": now_iso(),
            }
            self.store.insert_sequence(row)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        result = self.store.get_sequence(seq_id)
        assert result is not None
        return _public(result)

    def delete(self, sequence_id: str) -> str:
        """``deleted``, ``missing``, ``busy`` (queued or running jobs use it) or ``bundled``."""
        if sequence_id.startswith(SAMPLE_PREFIX):
            return "bundled" if sequence_id in self.samples() else "missing"
        outcome = self.store.delete_sequence(sequence_id)
        if outcome == "deleted":
            shutil.rmtree(self.settings.uploads_dir / sequence_id, ignore_errors=True)
        return outcome

    def clean(self) -> None:
        """At start-up: remove unfinished uploads and folders whose row was never written."""
        shutil.rmtree(self.tmp_dir, ignore_errors=True)
        shutil.rmtree(self.extract_dir, ignore_errors=True)
        self.settings.uploads_dir.mkdir(parents=True, exist_ok=True)
        known = {Path(p).parts[1] for p in self.store.sequence_paths() if len(Path(p).parts) > 1}
        for entry in self.settings.uploads_dir.iterdir():
            if entry.is_dir() and entry.name not in known:
                log.warning("removing orphaned upload folder %s", entry)
                shutil.rmtree(entry, ignore_errors=True)
        for part in ("reader", "service"):
            (self.extract_dir / part).mkdir(parents=True)

    def close(self) -> None:
        self._reads.shutdown(wait=False, cancel_futures=True)  # the files of cancelled reads: swept at start-up
        self.reader.close()


def _sample_has_poses(samples: Any, name: str) -> bool | None:
    """Whether a bundled ``.npz`` sample has ground-truth poses (its key list only; None if unknown)."""
    try:
        path = Path(samples.sample_path(name))
        if path.suffix != ".npz":
            return None
        with zipfile.ZipFile(path) as zf:
            return "poses.npy" in zf.namelist()
    except Exception:
        return None


def _clean(message: str, path: Path, filename: str) -> str:
    """A reader's message without server paths: the upload's temporary name becomes the uploaded
    file's name, and files extracted from an archive are named ``archive.zip:member``."""
    message = message.replace(str(path), filename).replace(path.name, filename)
    return _EXTRACTED.sub(f"{filename}:", message)


def _default_name(filename: str, suffix: str, summary: dict[str, Any]) -> str:
    stem = filename[: -len(suffix)] if filename.lower().endswith(suffix) else filename
    return stem or str(summary.get("name") or "sequence")


def _public(row: dict[str, Any]) -> dict[str, Any]:
    return {
        "id": row["id"],
        "name": row["name"],
        "source": "upload",
        "frames": row["frames"],
        "dims": row["dims"],
        "points": row["points"],
        "unit": row["unit"],
        "has_ground_truth": row["has_ground_truth"],
        "format": row["format"],
        "filename": row["filename"],
        "selection": row["selection"],
        "size_bytes": row["size_bytes"],
        "created_at": row["created_at"],
    }
