"""The durable job store: SQLite (stdlib ``sqlite3``, WAL) beside the data directory.

Tables: ``sequences`` (uploads), ``comparisons``, ``jobs`` (one row per run, in submission
order) and ``events`` (every event of every job, numbered per job from 1: the SSE ids).

Writes go through one connection guarded by a lock, in short transactions; reads use one
connection per thread, so readers never wait for the writer (WAL). Every status change of a
job is a conditional ``UPDATE`` plus a ``status`` event in the same transaction, so the log of
a job always ends with its final status and two threads can never both move the same job.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]
FINAL_STATUSES: frozenset[str] = frozenset({"succeeded", "failed", "cancelled", "interrupted"})
ACTIVE_STATUSES: frozenset[str] = frozenset({"queued", "running"})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sequences (
    id               TEXT PRIMARY KEY,
    name             TEXT NOT NULL,
    filename         TEXT NOT NULL,
    path             TEXT NOT NULL,
    format           TEXT NOT NULL,
    selection        TEXT,
    frames           INTEGER NOT NULL,
    dims             INTEGER NOT NULL,
    points           INTEGER NOT NULL,
    unit             TEXT NOT NULL,
    has_ground_truth INTEGER NOT NULL,
    size_bytes       INTEGER NOT NULL,
    created_at       TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS comparisons (
    id          TEXT PRIMARY KEY,
    sequence_id TEXT NOT NULL,
    methods     TEXT NOT NULL,
    created_at  TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS jobs (
    seq              INTEGER PRIMARY KEY AUTOINCREMENT,
    id               TEXT NOT NULL UNIQUE,
    sequence_id      TEXT NOT NULL,
    comparison_id    TEXT,
    method           TEXT NOT NULL,
    config           TEXT NOT NULL,
    status           TEXT NOT NULL,
    error            TEXT,
    metrics          TEXT,
    files            TEXT NOT NULL DEFAULT '[]',
    pid              INTEGER,
    exit_code        INTEGER,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    last_event_id    INTEGER NOT NULL DEFAULT 0,
    created_at       TEXT NOT NULL,
    started_at       TEXT,
    finished_at      TEXT
);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs (status, seq);
CREATE INDEX IF NOT EXISTS jobs_by_comparison ON jobs (comparison_id, seq);
CREATE INDEX IF NOT EXISTS jobs_by_sequence ON jobs (sequence_id, status);
CREATE TABLE IF NOT EXISTS events (
    job_id TEXT NOT NULL,
    id     INTEGER NOT NULL,
    kind   TEXT NOT NULL,
    data   TEXT NOT NULL,
    at     REAL NOT NULL,
    PRIMARY KEY (job_id, id)
) WITHOUT ROWID;
"""


_TABLES = ("sequences", "comparisons", "jobs", "events")
_INSERT_JOB = (
    "INSERT INTO jobs (id, sequence_id, comparison_id, method, config, status, created_at, last_event_id)"
    " VALUES (?, ?, ?, ?, ?, 'queued', ?, 1)"
)


def now_iso() -> str:
    """The current UTC time, ISO 8601 with microseconds."""
    return datetime.now(timezone.utc).isoformat()


@dataclass(frozen=True)
class StoredEvent:
    """One event of a job's log: ``id`` is its number within the job (1, 2, ...), ``at`` when it
    happened (``time.time()``: emitted by the worker, or the status change)."""

    job_id: str
    id: int
    kind: str
    data: str
    at: float

    @property
    def final_status(self) -> bool:
        """True for the ``status`` event that ends a job's log."""
        return self.kind == "status" and json.loads(self.data).get("status") in FINAL_STATUSES


@dataclass(frozen=True)
class EventIn:
    """An event to append to a job's log (its id is assigned by the store)."""

    job_id: str
    kind: str
    data: str
    at: float | None = None  # when it happened (``time.time()``); None: now


@dataclass(frozen=True)
class StatusChange:
    """A conditional status change: applied only if the job is in one of ``from_statuses``."""

    job_id: str
    from_statuses: tuple[str, ...]
    status: str
    error: str | None = None
    fields: tuple[tuple[str, Any], ...] = ()


_JOB_FIELDS = {"config", "metrics", "files", "pid", "exit_code", "started_at", "finished_at", "cancel_requested"}


def status_data(status: str, *, error: str | None = None, **extra: Any) -> str:
    """JSON of a ``status`` event."""
    return json.dumps(
        {"kind": "status", "status": status, "error": error, **extra}, allow_nan=False, separators=(",", ":")
    )


class Store:
    """SQLite store of sequences, comparisons, jobs and events. Thread-safe."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._local = threading.local()
        self._readers: list[sqlite3.Connection] = []
        self._readers_lock = threading.Lock()
        self._closed = False
        self._writer = self._connect()
        self._writer.executescript(_SCHEMA)

    # ---- connections ---------------------------------------------------------------------
    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, timeout=30, isolation_level=None, check_same_thread=False)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.execute("PRAGMA foreign_keys=ON")
        return conn

    def _reader(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            if self._closed:
                raise RuntimeError("the store is closed")
            conn = self._connect()
            conn.execute("PRAGMA query_only=ON")
            self._local.conn = conn
            with self._readers_lock:
                self._readers.append(conn)
        return conn

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            if self._closed:
                raise RuntimeError("the store is closed")
            conn = self._writer
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._writer.close()
        with self._readers_lock:
            for conn in self._readers:
                conn.close()
            self._readers.clear()

    # ---- sequences -----------------------------------------------------------------------
    def insert_sequence(self, row: dict[str, Any]) -> None:
        cols = ", ".join(row)
        marks = ", ".join("?" for _ in row)
        with self._write() as db:
            db.execute(f"INSERT INTO sequences ({cols}) VALUES ({marks})", tuple(row.values()))

    def get_sequence(self, sequence_id: str) -> dict[str, Any] | None:
        row = self._reader().execute("SELECT * FROM sequences WHERE id = ?", (sequence_id,)).fetchone()
        return _sequence(row) if row else None

    def list_sequences(self) -> list[dict[str, Any]]:
        rows = self._reader().execute("SELECT * FROM sequences ORDER BY created_at, id").fetchall()
        return [_sequence(r) for r in rows]

    def sequence_paths(self) -> set[str]:
        return {r["path"] for r in self._reader().execute("SELECT path FROM sequences")}

    def delete_sequence(self, sequence_id: str) -> Literal["deleted", "missing", "busy"]:
        """Delete an uploaded sequence's row unless queued or running jobs use it."""
        with self._write() as db:
            if db.execute("SELECT 1 FROM sequences WHERE id = ?", (sequence_id,)).fetchone() is None:
                return "missing"
            busy = db.execute(
                "SELECT 1 FROM jobs WHERE sequence_id = ? AND status IN ('queued', 'running') LIMIT 1",
                (sequence_id,),
            ).fetchone()
            if busy:
                return "busy"
            db.execute("DELETE FROM sequences WHERE id = ?", (sequence_id,))
            return "deleted"

    # ---- jobs ----------------------------------------------------------------------------
    def insert_jobs(self, jobs: list[dict[str, Any]], comparison: dict[str, Any] | None = None) -> list[StoredEvent]:
        """Insert queued jobs (and their comparison) in one transaction; returns their first events."""
        created: list[StoredEvent] = []
        at = time.time()
        with self._write() as db:
            if comparison is not None:
                db.execute(
                    "INSERT INTO comparisons (id, sequence_id, methods, created_at) VALUES (?, ?, ?, ?)",
                    (
                        comparison["id"],
                        comparison["sequence_id"],
                        json.dumps(comparison["methods"]),
                        comparison["created_at"],
                    ),
                )
            for job in jobs:
                db.execute(
                    _INSERT_JOB,
                    (
                        job["id"],
                        job["sequence_id"],
                        job.get("comparison_id"),
                        job["method"],
                        job["config"],
                        job["created_at"],
                    ),
                )
                data = status_data("queued")
                db.execute(
                    "INSERT INTO events (job_id, id, kind, data, at) VALUES (?, 1, 'status', ?, ?)",
                    (job["id"], data, at),
                )
                created.append(StoredEvent(job["id"], 1, "status", data, at))
        return created

    def get_job(self, job_id: str) -> dict[str, Any] | None:
        row = self._reader().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _job(row) if row else None

    def list_jobs(
        self,
        *,
        status: str | None = None,
        sequence_id: str | None = None,
        comparison_id: str | None = None,
        limit: int = 100,
        offset: int = 0,
        newest_first: bool = True,
    ) -> tuple[list[dict[str, Any]], int]:
        where, args = [], []
        for col, value in (("status", status), ("sequence_id", sequence_id), ("comparison_id", comparison_id)):
            if value is not None:
                where.append(f"{col} = ?")
                args.append(value)
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        db = self._reader()
        count = db.execute(f"SELECT COUNT(*) FROM jobs{clause}", args).fetchone()[0]
        order = "DESC" if newest_first else "ASC"
        rows = db.execute(f"SELECT * FROM jobs{clause} ORDER BY seq {order} LIMIT ? OFFSET ?", [*args, limit, offset])
        return [_job(r) for r in rows.fetchall()], int(count)

    def next_queued(self, limit: int) -> list[dict[str, Any]]:
        """The oldest queued jobs (FIFO)."""
        rows = self._reader().execute("SELECT * FROM jobs WHERE status = 'queued' ORDER BY seq LIMIT ?", (limit,))
        return [_job(r) for r in rows.fetchall()]

    def count_active_for_sequence(self, sequence_id: str) -> int:
        row = (
            self._reader()
            .execute(
                "SELECT COUNT(*) FROM jobs WHERE sequence_id = ? AND status IN ('queued', 'running')", (sequence_id,)
            )
            .fetchone()
        )
        return int(row[0])

    def set_job_fields(self, job_id: str, **fields: Any) -> None:
        unknown = set(fields) - _JOB_FIELDS
        if unknown:
            raise ValueError(f"not settable: {sorted(unknown)}")
        sets = ", ".join(f"{k} = ?" for k in fields)
        with self._write() as db:
            db.execute(f"UPDATE jobs SET {sets} WHERE id = ?", (*(_encode(k, v) for k, v in fields.items()), job_id))

    def get_comparison(self, comparison_id: str) -> dict[str, Any] | None:
        row = self._reader().execute("SELECT * FROM comparisons WHERE id = ?", (comparison_id,)).fetchone()
        if row is None:
            return None
        out = dict(row)
        out["methods"] = json.loads(out["methods"])
        return out

    # ---- the event log -------------------------------------------------------------------
    def apply(self, items: Iterable[EventIn | StatusChange]) -> list[StoredEvent]:
        """Append events and apply status changes, in order, in one transaction.

        A `StatusChange` whose job is not in one of its ``from_statuses`` is skipped (it lost
        a race, e.g. a cancel against a finish). Returns the events stored, in order.
        """
        stored: list[StoredEvent] = []
        at = time.time()
        with self._write() as db:
            for item in items:
                if isinstance(item, StatusChange):
                    ev = self._change_status(db, item, at)
                    if ev is not None:
                        stored.append(ev)
                    continue
                row = db.execute("SELECT last_event_id FROM jobs WHERE id = ?", (item.job_id,)).fetchone()
                if row is None:
                    continue
                eid = row[0] + 1
                db.execute("UPDATE jobs SET last_event_id = ? WHERE id = ?", (eid, item.job_id))
                when = at if item.at is None else item.at
                db.execute(
                    "INSERT INTO events (job_id, id, kind, data, at) VALUES (?, ?, ?, ?, ?)",
                    (item.job_id, eid, item.kind, item.data, when),
                )
                stored.append(StoredEvent(item.job_id, eid, item.kind, item.data, when))
        return stored

    def _change_status(self, db: sqlite3.Connection, change: StatusChange, at: float) -> StoredEvent | None:
        fields = dict(change.fields)
        if change.status in FINAL_STATUSES:
            fields.setdefault("finished_at", now_iso())
        if change.status == "running":
            fields.setdefault("started_at", now_iso())
        unknown = set(fields) - _JOB_FIELDS
        if unknown:
            raise ValueError(f"not settable: {sorted(unknown)}")
        sets = ", ".join(
            ["status = ?", "error = ?", "last_event_id = last_event_id + 1"] + [f"{k} = ?" for k in fields]
        )
        marks = ", ".join("?" for _ in change.from_statuses)
        cur = db.execute(
            f"UPDATE jobs SET {sets} WHERE id = ? AND status IN ({marks}) RETURNING last_event_id, exit_code",
            (
                change.status,
                change.error,
                *(_encode(k, v) for k, v in fields.items()),
                change.job_id,
                *change.from_statuses,
            ),
        )
        row = cur.fetchone()
        cur.fetchall()
        if row is None:
            return None
        eid = row[0]
        extra = {"exit_code": row[1]} if row[1] is not None else {}
        data = status_data(change.status, error=change.error, **extra)
        db.execute(
            "INSERT INTO events (job_id, id, kind, data, at) VALUES (?, ?, 'status', ?, ?)",
            (change.job_id, eid, data, at),
        )
        return StoredEvent(change.job_id, eid, "status", data, at)

    def events_after(self, job_id: str, after: int, limit: int = 1000) -> list[StoredEvent]:
        rows = self._reader().execute(
            "SELECT job_id, id, kind, data, at FROM events WHERE job_id = ? AND id > ? ORDER BY id LIMIT ?",
            (job_id, after, limit),
        )
        return [StoredEvent(r[0], r[1], r[2], r[3], r[4]) for r in rows.fetchall()]

    def counts(self) -> dict[str, int]:
        """Rows per table (for health checks and tests)."""
        db = self._reader()
        return {t: int(db.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0]) for t in _TABLES}

    # ---- start-up ------------------------------------------------------------------------
    def jobs_with_status(self, status: str) -> list[dict[str, Any]]:
        rows = self._reader().execute("SELECT * FROM jobs WHERE status = ? ORDER BY seq", (status,))
        return [_job(r) for r in rows.fetchall()]


def _encode(key: str, value: Any) -> Any:
    if key in ("config", "metrics", "files"):
        return json.dumps(value, allow_nan=False) if value is not None else None
    if key == "cancel_requested":
        return int(bool(value))
    return value


def _sequence(row: sqlite3.Row) -> dict[str, Any]:
    out = dict(row)
    out["has_ground_truth"] = bool(out["has_ground_truth"])
    return out


def _job(row: sqlite3.Row) -> dict[str, Any]:
    out = dict(row)
    out["config"] = json.loads(out["config"])
    out["metrics"] = json.loads(out["metrics"]) if out["metrics"] else None
    out["files"] = json.loads(out["files"]) if out["files"] else []
    out["cancel_requested"] = bool(out["cancel_requested"])
    return out
