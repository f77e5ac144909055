"""Job records in SQLite: state, stage, progress, error and timestamps that survive restarts of
the API and the workers (several processes share the file; WAL mode, one connection per call).

States: ``queued`` -> ``running`` -> ``succeeded`` | ``failed`` | ``cancelled`` (a queued job
can be cancelled directly; a worker found dead sends a running job back to ``queued``).
Stages, in order: ``preprocess`` (decode + detect), ``align`` (body-model fit), ``train``,
``export`` (publish the avatar). ``completed_stage`` is the last one whose result is on disk.

Kinds: an ``avatar`` job makes the avatar ``avatar_id`` from a video; an ``animation`` job makes
an animation of an existing avatar (``jobs.animation``): its ``avatar_id`` column holds the id of
the animation it makes (the column is the job's unique output id) and ``options["avatar_id"]``
the avatar it animates. Its stages: ``preprocess``, ``align`` (the driving video), ``render``,
``export``.
"""

from __future__ import annotations

import json
import sqlite3
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL = ("succeeded", "failed", "cancelled")
STAGES = ("preprocess", "align", "train", "export")
KINDS = ("avatar", "animation")
STAGES_OF = {"avatar": STAGES, "animation": ("preprocess", "align", "render", "export")}

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    avatar_id TEXT NOT NULL UNIQUE,
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
    avatar_deleted INTEGER NOT NULL DEFAULT 0,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    updated_at REAL NOT NULL,
    heartbeat_at REAL,
    kind TEXT NOT NULL DEFAULT 'avatar'
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state);
"""


def new_id() -> str:
    """A fresh id: 32 lowercase hex characters (never a path component to worry about)."""
    return uuid.uuid4().hex


def is_valid_id(value: str) -> bool:
    return len(value) == 32 and all(c in "0123456789abcdef" for c in value)


@dataclass
class JobRecord:
    """One row of ``jobs`` (timestamps: Unix seconds)."""

    id: str
    avatar_id: str
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
    avatar_deleted: bool = False
    started_at: float | None = None
    finished_at: float | None = None
    heartbeat_at: float | None = None
    kind: str = "avatar"

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> JobRecord:
        d = dict(row)
        d["options"] = json.loads(d["options"])
        d["cancel_requested"] = bool(d["cancel_requested"])
        d["avatar_deleted"] = bool(d["avatar_deleted"])
        return cls(**d)


class JobStore:
    """The job table at ``path`` (created on first use)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(_SCHEMA)
            columns = {row["name"] for row in db.execute("PRAGMA table_info(jobs)")}
            if "kind" not in columns:  # a table made before animation jobs
                db.execute("ALTER TABLE jobs ADD COLUMN kind TEXT NOT NULL DEFAULT 'avatar'")

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            yield db
        finally:
            db.close()

    # -- reads ---------------------------------------------------------------------------------
    def get(self, job_id: str) -> JobRecord | None:
        with self._connect() as db:
            row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return JobRecord.from_row(row) if row else None

    def by_avatar(self, avatar_id: str, kind: str = "avatar") -> JobRecord | None:
        """The job that made ``avatar_id`` (for ``kind="animation"``: the animation with that id)."""
        with self._connect() as db:
            row = db.execute(
                "SELECT * FROM jobs WHERE avatar_id = ? AND avatar_deleted = 0 AND kind = ?",
                (avatar_id, kind),
            ).fetchone()
        return JobRecord.from_row(row) if row else None

    def list(self, states: tuple[str, ...] | None = None, with_deleted: bool = False,
             kind: str | None = None) -> list[JobRecord]:  # fmt: skip
        query, args = "SELECT * FROM jobs WHERE 1 = 1", []
        if kind is not None:
            query += " AND kind = ?"
            args.append(kind)
        if states:
            query += f" AND state IN ({','.join('?' * len(states))})"
            args += list(states)
        if not with_deleted:
            query += " AND avatar_deleted = 0"
        with self._connect() as db:
            rows = db.execute(query + " ORDER BY created_at", args).fetchall()
        return [JobRecord.from_row(r) for r in rows]

    # -- writes --------------------------------------------------------------------------------
    def create(self, options: dict[str, Any], filename: str | None = None,
               job_id: str | None = None, avatar_id: str | None = None,
               kind: str = "avatar") -> JobRecord:  # fmt: skip
        if kind not in KINDS:
            raise ValueError(f"unknown job kind {kind!r}; choose one of {KINDS}")
        now = time.time()
        job = JobRecord(
            id=job_id or new_id(), avatar_id=avatar_id or new_id(), state="queued", options=options,
            created_at=now, updated_at=now, filename=filename, message="waiting for a worker", kind=kind,
        )  # fmt: skip
        with self._connect() as db:
            db.execute(
                "INSERT INTO jobs (id, avatar_id, kind, state, options, filename, message, created_at,"
                " updated_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (job.id, job.avatar_id, kind, job.state, json.dumps(options), filename, job.message, now,
                 now),  # fmt: skip
            )
        return job

    def update(self, job_id: str, *, where_state: tuple[str, ...] | None = None, **fields: Any) -> bool:
        """Set ``fields`` (column names); only if the job's state is in ``where_state`` when given.
        Returns whether a row changed (the compare-and-set that claims and cancels jobs)."""
        fields["updated_at"] = time.time()
        if "options" in fields:
            fields["options"] = json.dumps(fields["options"])
        sets = ", ".join(f"{k} = ?" for k in fields)
        query, args = f"UPDATE jobs SET {sets} WHERE id = ?", [*fields.values(), job_id]
        if where_state:
            query += f" AND state IN ({','.join('?' * len(where_state))})"
            args += list(where_state)
        with self._connect() as db:
            return db.execute(query, args).rowcount == 1

    def claim(self, job_id: str, worker: str) -> JobRecord | None:
        """Atomically move a queued job to running for ``worker`` (None if someone else has it)."""
        now = time.time()
        with self._connect() as db:
            changed = db.execute(
                "UPDATE jobs SET state = 'running', worker = ?, attempts = attempts + 1,"
                " started_at = COALESCE(started_at, ?), heartbeat_at = ?, updated_at = ?, message = NULL"
                " WHERE id = ? AND state = 'queued' AND cancel_requested = 0",
                (worker, now, now, now, job_id),
            ).rowcount
        return self.get(job_id) if changed == 1 else None

    def finish(self, job_id: str, state: str, error: str | None = None, message: str | None = None,
               from_states: tuple[str, ...] = ("queued", "running")) -> bool:  # fmt: skip
        """Move a job to a terminal state (only from ``from_states``)."""
        if state not in TERMINAL:
            raise ValueError(f"{state!r} is not a terminal state")
        extra: dict[str, Any] = {"progress": 1.0, "eta_s": 0.0} if state == "succeeded" else {"eta_s": None}
        return self.update(
            job_id, where_state=from_states, state=state, error=error, message=message,
            finished_at=time.time(), **extra,
        )  # fmt: skip

    def heartbeat(self, job_id: str, worker: str) -> None:
        with self._connect() as db:
            db.execute(
                "UPDATE jobs SET heartbeat_at = ? WHERE id = ? AND worker = ? AND state = 'running'",
                (time.time(), job_id, worker),
            )

    def delete(self, job_id: str) -> None:
        with self._connect() as db:
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
