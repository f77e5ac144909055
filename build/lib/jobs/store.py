"""Job records: state, stage, progress, error and timestamps that survive restarts of the API and
the workers. ``JobStore`` is the contract; ``SqliteJobStore`` keeps the records in SQLite (several
processes on one host share the file; WAL mode, one connection per call; WAL needs shared memory
between the processes, so the file must be on a local disk: it refuses a network file system
rather than corrupt it), ``jobs.store_redis.RedisJobStore`` in Redis (API and workers on several
hosts); ``jobs.backends.open_store`` picks one from the configuration.

States: ``queued`` -> ``running`` -> ``succeeded`` | ``failed`` | ``cancelled`` (a queued job
can be cancelled directly; a worker found dead sends a running job back to ``queued``).
Kinds (``jobs.kinds``) name a job's stages, in order, and what it makes, whose id is the record's
unique ``output_id``: an ``avatar`` job makes that avatar from a video (``preprocess``,
``align``, ``train``, ``export``); an ``animation`` job makes that animation of an existing avatar,
``options["avatar_id"]`` (``jobs.animation``). ``output_deleted``: the output was deleted;
``stage``: the stage running (or last run); ``completed_stage``: the last one whose result is on
disk.

Ownership: a running job belongs to the worker that claimed it (``worker``). Every write a worker
makes is conditional on still owning it (``owner=``), and recovery's writes are conditional on the
exact record it judged (``expect=``: state, worker and heartbeat), so a worker that lost its job
(recovery gave it to another) can no longer change it: its writes return False / raise ``JobLost``.
"""

from __future__ import annotations

import functools
import json
import logging
import sqlite3
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

logger = logging.getLogger("eva.jobs")

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL = ("succeeded", "failed", "cancelled")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    output_id TEXT NOT NULL UNIQUE,
    state TEXT NOT NULL,
    stage TEXT,
    completed_stage TEXT,
    progress REAL NOT NULL DEFAULT 0,
    eta_s REAL,
    message TEXT,
    error TEXT,
    options TEXT NOT NULL,
    filename TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    worker TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    output_deleted INTEGER NOT NULL DEFAULT 0,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    updated_at REAL NOT NULL,
    heartbeat_at REAL,
    enqueued_at REAL,
    kind TEXT NOT NULL DEFAULT 'avatar',
    account TEXT,
    worker_losses INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state);
"""
# Columns renamed and added since the first release: done to an older file when it is opened.
_RENAMED_COLUMNS = {"avatar_id": "output_id", "avatar_deleted": "output_deleted"}
_ADDED_COLUMNS = {
    "enqueued_at": "REAL",
    "kind": "TEXT NOT NULL DEFAULT 'avatar'",
    "account": "TEXT",
    "worker_losses": "INTEGER NOT NULL DEFAULT 0",
}
# File systems where SQLite's WAL (shared-memory index, POSIX locks) is unsafe.
NETWORK_FILESYSTEMS = frozenset(
    {
        "nfs",
        "nfs4",
        "cifs",
        "smb3",
        "smbfs",
        "ceph",
        "glusterfs",
        "fuse.glusterfs",
        "fuse.sshfs",
        "fuse.s3fs",
        "lustre",
        "gpfs",
        "afs",
        "9p",
        "fuse.rclone",
        "beegfs",
        "ocfs2",
    }
)
_BUSY_RETRIES = 4


class JobLost(Exception):
    """This worker no longer owns the job: recovery gave it to another worker, or it ended."""


class JobStoreError(RuntimeError):
    """The job records cannot be kept where they were asked to be (see the message)."""


def new_id() -> str:
    """A fresh id: 32 lowercase hex characters (never a path component to worry about)."""
    return uuid.uuid4().hex


def is_valid_id(value: str) -> bool:
    return len(value) == 32 and all(c in "0123456789abcdef" for c in value)


@dataclass
class JobRecord:
    """One row of ``jobs`` (timestamps: Unix seconds)."""

    id: str
    output_id: str
    state: str
    options: dict[str, Any]
    created_at: float
    updated_at: float
    stage: str | None = None
    completed_stage: str | None = None
    progress: float = 0.0
    eta_s: float | None = None
    message: str | None = None
    error: str | None = None
    filename: str | None = None
    attempts: int = 0
    worker: str | None = None
    cancel_requested: bool = False
    output_deleted: bool = False
    started_at: float | None = None
    finished_at: float | None = None
    heartbeat_at: float | None = None
    enqueued_at: float | None = None
    kind: str = "avatar"
    account: str | None = None
    """The owner the job belongs to (``service.accounts``; None: the local mode, or older)."""
    worker_losses: int = 0
    """Attempts that ended because the worker under them died (``JobsConfig.max_worker_losses``)."""

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> JobRecord:
        d = dict(row)
        d["options"] = json.loads(d["options"])
        return cls.from_dict(d)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> JobRecord:
        d = {_RENAMED_COLUMNS.get(k, k): v for k, v in d.items()}  # a record written before the rename
        d = {
            **d,
            "cancel_requested": bool(d["cancel_requested"]),
            "output_deleted": bool(d["output_deleted"]),
        }
        return cls(**d)

    def matches(
        self,
        where_state: tuple[str, ...] | None = None,
        owner: str | None = None,
        expect: JobRecord | None = None,
    ) -> bool:
        """The conditions of ``JobStore.update``, checked against this record."""
        if where_state and self.state not in where_state:
            return False
        if owner is not None and (self.state != "running" or self.worker != owner):
            return False
        if expect is not None and (self.state, self.worker, self.heartbeat_at) != (
            expect.state,
            expect.worker,
            expect.heartbeat_at,
        ):
            return False
        return True


def new_record(
    options: dict[str, Any],
    filename: str | None,
    job_id: str | None,
    output_id: str | None,
    kind: str,
    account: str | None,
) -> JobRecord:
    """A queued job's first record (``JobStore.create``)."""
    if not kind.isidentifier():  # which kinds exist is ``jobs.kinds``'; a record holds any name
        raise ValueError(f"a job kind is a name, got {kind!r}")
    now = time.time()
    return JobRecord(
        id=job_id or new_id(),
        output_id=output_id or new_id(),
        state="queued",
        options=options,
        created_at=now,
        updated_at=now,
        filename=filename,
        message="waiting for a worker",
        kind=kind,
        account=account,
    )


def finished_fields(state: str, error: str | None, message: str | None) -> dict[str, Any]:
    """What ``JobStore.finish`` sets."""
    if state not in TERMINAL:
        raise ValueError(f"{state!r} is not a terminal state")
    extra: dict[str, Any] = {"progress": 1.0, "eta_s": 0.0} if state == "succeeded" else {"eta_s": None}
    return {"state": state, "error": error, "message": message, "finished_at": time.time(), **extra}


def purgeable(job: JobRecord, finished_before: float) -> bool:
    """A record ``JobStore.purge`` deletes: ended before then, and left nothing to serve."""
    ended = job.finished_at is not None and job.finished_at < finished_before
    gone = job.state in ("failed", "cancelled") or (job.state == "succeeded" and job.output_deleted)
    return ended and gone


def _retry_busy(method):
    """Retry a store operation when SQLite stays busy or locked past its timeout (another process
    holding a long write), with a short backoff; other errors pass through."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        for attempt in range(_BUSY_RETRIES):
            try:
                return method(self, *args, **kwargs)
            except sqlite3.OperationalError as err:
                transient = "locked" in str(err) or "busy" in str(err)
                if not transient or attempt == _BUSY_RETRIES - 1:
                    raise
                logger.warning("job store busy (%s); retrying %s", err, method.__name__)
                time.sleep(0.2 * 2**attempt)
        raise AssertionError("unreachable")

    return wrapper


def filesystem_type(path: Path) -> str | None:
    """The type of the file system holding ``path`` (Linux /proc/self/mounts), or None."""
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return None
    target = str(path.resolve())
    best, kind = "", None
    for line in mounts:
        parts = line.split()
        if len(parts) < 3:
            continue
        point = parts[1].replace("\\040", " ")
        inside = target == point or target.startswith(point.rstrip("/") + "/")
        if inside and len(point) >= len(best):
            best, kind = point, parts[2]
    return kind


class JobStore(ABC):
    """The job records (see the module docstring); every method is safe to call from several
    processes and hosts at once."""

    # -- reads ---------------------------------------------------------------------------------
    @abstractmethod
    def get(self, job_id: str) -> JobRecord | None: ...

    @abstractmethod
    def by_output(
        self, output_id: str, with_deleted: bool = False, kind: str | None = "avatar"
    ) -> JobRecord | None:
        """The job that made ``output_id`` (for ``kind="animation"``: the animation with that id;
        ``kind=None``: either)."""

    @abstractmethod
    def list(
        self,
        states: tuple[str, ...] | None = None,
        with_deleted: bool = False,
        kind: str | None = None,
        account: str | None = None,
    ) -> list[JobRecord]:
        """Jobs oldest first, of these ``states``, ``kind`` and ``account`` (None: any)."""

    @abstractmethod
    def queued(self, account: str | None = None) -> int:
        """Jobs waiting for a worker (of ``account``; None: all)."""

    @abstractmethod
    def counts(self) -> dict[str, int]:
        """Jobs per state."""

    # -- writes --------------------------------------------------------------------------------
    @abstractmethod
    def create(
        self,
        options: dict[str, Any],
        filename: str | None = None,
        job_id: str | None = None,
        output_id: str | None = None,
        kind: str = "avatar",
        account: str | None = None,
    ) -> JobRecord:
        """A new queued job; its id and its ``output_id`` are unique."""

    @abstractmethod
    def update(
        self,
        job_id: str,
        *,
        where_state: tuple[str, ...] | None = None,
        owner: str | None = None,
        expect: JobRecord | None = None,
        **fields: Any,
    ) -> bool:
        """Set ``fields`` (column names) if the job still matches, and say whether it did (the
        compare-and-set behind claims, cancels and recovery). Conditions: ``where_state``, the
        job's state is one of these; ``owner``, it is running and claimed by this worker;
        ``expect``, it is still exactly as in this record (state, worker and heartbeat)."""

    @abstractmethod
    def claim(self, job_id: str, worker: str) -> JobRecord | None:
        """Atomically move a queued job to running for ``worker`` (None if someone else has it)."""

    @abstractmethod
    def heartbeat(self, job_id: str, worker: str) -> JobRecord | None:
        """Mark the job alive; returns its record, or None when ``worker`` no longer owns it."""

    @abstractmethod
    def delete(self, job_id: str) -> None: ...

    @abstractmethod
    def purge(self, finished_before: float) -> list[JobRecord]:
        """Delete the records of jobs that ended before ``finished_before`` and left nothing to
        serve (failed, cancelled, or their avatar deleted); returns them."""

    def finish(
        self,
        job_id: str,
        state: str,
        error: str | None = None,
        message: str | None = None,
        from_states: tuple[str, ...] = ("queued", "running"),
        owner: str | None = None,
        expect: JobRecord | None = None,
    ) -> bool:
        """Move a job to a terminal state (only from ``from_states``; ``owner`` / ``expect`` as in
        ``update``)."""
        fields = finished_fields(state, error, message)
        return self.update(job_id, where_state=from_states, owner=owner, expect=expect, **fields)


class SqliteJobStore(JobStore):
    """The job table at ``path`` (created on first use). ``timeout``: seconds a call waits for
    another process's write lock before it is retried."""

    def __init__(self, path: str | Path, timeout: float = 10.0) -> None:
        self.path = Path(path)
        self.timeout = timeout
        self.path.parent.mkdir(parents=True, exist_ok=True)
        kind = filesystem_type(self.path.parent)
        if kind in NETWORK_FILESYSTEMS:
            raise JobStoreError(
                f"job records (SQLite, WAL) need a local disk, but {self.path.parent} is on {kind}: run the "
                "API and the workers on one host with the data dir on a local disk, or keep the records "
                "in Redis (EVA_RECORDS_URL; docs/deployment.md, Several hosts)"
            )
        self._init()

    @_retry_busy
    def _init(self) -> None:
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(_SCHEMA)
            have = {row["name"] for row in db.execute("PRAGMA table_info(jobs)")}
            for old, new in _RENAMED_COLUMNS.items():
                if old in have:
                    db.execute(f"ALTER TABLE jobs RENAME COLUMN {old} TO {new}")
                    have = (have - {old}) | {new}
            for name, kind in _ADDED_COLUMNS.items():
                if name not in have:
                    db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {kind}")

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        db = sqlite3.connect(self.path, timeout=self.timeout, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            yield db
        finally:
            db.close()

    # -- reads ---------------------------------------------------------------------------------
    @_retry_busy
    def get(self, job_id: str) -> JobRecord | None:
        with self._connect() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return JobRecord.from_row(row) if row else None

    @_retry_busy
    def by_output(
        self, output_id: str, with_deleted: bool = False, kind: str | None = "avatar"
    ) -> JobRecord | None:
        query, args = "SELECT * FROM jobs WHERE output_id = ?", [output_id]
        if not with_deleted:
            query += " AND output_deleted = 0"
        if kind is not None:
            query += " AND kind = ?"
            args.append(kind)
        with self._connect() as db:
            row = db.execute(query, args).fetchone()
        return JobRecord.from_row(row) if row else None

    @_retry_busy
    def list(
        self,
        states: tuple[str, ...] | None = None,
        with_deleted: bool = False,
        kind: str | None = None,
        account: str | None = None,
    ) -> list[JobRecord]:
        query, args = "SELECT * FROM jobs WHERE 1 = 1", []
        if account is not None:
            query += " AND account = ?"
            args.append(account)
        if kind is not None:
            query += " AND kind = ?"
            args.append(kind)
        if states:
            query += f" AND state IN ({','.join('?' * len(states))})"
            args += list(states)
        if not with_deleted:
            query += " AND output_deleted = 0"
        with self._connect() as db:
            rows = db.execute(query + " ORDER BY created_at", args).fetchall()
        return [JobRecord.from_row(r) for r in rows]

    @_retry_busy
    def queued(self, account: str | None = None) -> int:
        query, args = "SELECT COUNT(*) FROM jobs WHERE state = 'queued'", []
        if account is not None:
            query, args = query + " AND account = ?", [account]
        with self._connect() as db:
            return int(db.execute(query, args).fetchone()[0])

    @_retry_busy
    def counts(self) -> dict[str, int]:
        """Jobs per state (one indexed query, not a row per job)."""
        counts = dict.fromkeys(STATES, 0)
        with self._connect() as db:
            for row in db.execute("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state"):
                counts[row["state"]] = row["n"]
        return counts

    # -- writes --------------------------------------------------------------------------------
    @_retry_busy
    def create(
        self,
        options: dict[str, Any],
        filename: str | None = None,
        job_id: str | None = None,
        output_id: str | None = None,
        kind: str = "avatar",
        account: str | None = None,
    ) -> JobRecord:
        job = new_record(options, filename, job_id, output_id, kind, account)
        now = job.created_at
        row = (job.id, job.output_id, kind, job.state, json.dumps(options), filename, job.message, now, now)
        with self._connect() as db:
            db.execute(
                "INSERT INTO jobs (id, output_id, kind, state, options, filename, message, created_at,"
                " updated_at, account) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (*row, account),
            )
        return job

    @_retry_busy
    def update(
        self,
        job_id: str,
        *,
        where_state: tuple[str, ...] | None = None,
        owner: str | None = None,
        expect: JobRecord | None = None,
        **fields: Any,
    ) -> bool:
        fields["updated_at"] = time.time()
        if "options" in fields:
            fields["options"] = json.dumps(fields["options"])
        sets = ", ".join(f"{k} = ?" for k in fields)
        query, args = f"UPDATE jobs SET {sets} WHERE id = ?", [*fields.values(), job_id]
        if where_state:
            query += f" AND state IN ({','.join('?' * len(where_state))})"
            args += list(where_state)
        if owner is not None:
            query += " AND state = 'running' AND worker = ?"
            args.append(owner)
        if expect is not None:
            query += " AND state = ? AND worker IS ? AND heartbeat_at IS ?"
            args += [expect.state, expect.worker, expect.heartbeat_at]
        with self._connect() as db:
            return db.execute(query, args).rowcount == 1

    @_retry_busy
    def claim(self, job_id: str, worker: str) -> JobRecord | None:
        now = time.time()
        with self._connect() as db:
            changed = db.execute(
                "UPDATE jobs SET state = 'running', worker = ?, attempts = attempts + 1,"
                " started_at = COALESCE(started_at, ?), heartbeat_at = ?, updated_at = ?, message = NULL"
                " WHERE id = ? AND state = 'queued' AND cancel_requested = 0",
                (worker, now, now, now, job_id),
            ).rowcount
        return self.get(job_id) if changed == 1 else None

    @_retry_busy
    def heartbeat(self, job_id: str, worker: str) -> JobRecord | None:
        with self._connect() as db:
            changed = db.execute(
                "UPDATE jobs SET heartbeat_at = ? WHERE id = ? AND worker = ? AND state = 'running'",
                (time.time(), job_id, worker),
            ).rowcount
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone() if changed else None
        return JobRecord.from_row(row) if row else None

    @_retry_busy
    def delete(self, job_id: str) -> None:
        with self._connect() as db:
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))

    @_retry_busy
    def purge(self, finished_before: float) -> list[JobRecord]:
        where = "state IN ('failed', 'cancelled') OR (state = 'succeeded' AND output_deleted = 1)"
        with self._connect() as db:
            rows = db.execute(
                f"SELECT * FROM jobs WHERE finished_at < ? AND ({where})", (finished_before,)
            ).fetchall()
            db.executemany(
                "DELETE FROM jobs WHERE id = ? AND finished_at < ?",
                [(r["id"], finished_before) for r in rows],
            )
        return [JobRecord.from_row(r) for r in rows]
