"""``RedisJobStore``: the job records in Redis, so that the API and workers on several hosts share
them (``JobsConfig.records_url``; SQLite needs one host's local disk).

Keys, under ``<prefix>`` (``eva:records`` by default):

- ``<prefix>:job:<id>``: the record, as JSON (``JobRecord``'s fields);
- ``<prefix>:output:<output_id>``: the id of the job that makes that avatar or animation (what
  SQLite's UNIQUE column keeps unique);
- ``<prefix>:ids``: every job id, scored by its creation time (listings are oldest first).

Every conditional write (claims, ownership, recovery's ``expect=``) is an optimistic transaction:
WATCH the record, check the condition on what was read, then MULTI/EXEC the new value; a write by
another process in between makes EXEC fail and the check runs again on the new record. Listings
read every record (one MGET per 500): a service's job table is thousands of rows, not millions.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterator
from typing import Any

from jobs.store import STATES, JobRecord, JobStore, new_record, purgeable

_BATCH = 500
_FIELDS = frozenset(f.name for f in dataclasses.fields(JobRecord))


class DuplicateJobError(ValueError):
    """A job with this id, or making this output id, exists already."""


class RedisJobStore(JobStore):
    """The records in the Redis at ``url`` (``redis://[:password@]host:port/db``), under ``prefix``."""

    def __init__(self, url: str, prefix: str = "eva:records") -> None:
        from redis import Redis
        from redis.backoff import ExponentialBackoff
        from redis.exceptions import ConnectionError, TimeoutError
        from redis.retry import Retry

        self.prefix = prefix
        # A dropped connection or a Redis restart is retried, as SQLite's busy file is.
        self.redis = Redis.from_url(
            url,
            retry=Retry(ExponentialBackoff(cap=2.0, base=0.1), 4),
            retry_on_error=[ConnectionError, TimeoutError],
            health_check_interval=30,
            socket_timeout=10,
        )

    def _key(self, job_id: str) -> str:
        return f"{self.prefix}:job:{job_id}"

    def _output_key(self, output_id: str) -> str:
        return f"{self.prefix}:output:{output_id}"

    @property
    def _ids(self) -> str:
        return f"{self.prefix}:ids"

    @staticmethod
    def _decode(raw: bytes | str | None) -> JobRecord | None:
        return JobRecord.from_dict(json.loads(raw)) if raw else None

    @staticmethod
    def _encode(job: JobRecord) -> str:
        return json.dumps(dataclasses.asdict(job))

    def _all(self) -> Iterator[JobRecord]:
        """Every record, oldest first."""
        ids = [i.decode() for i in self.redis.zrange(self._ids, 0, -1)]
        for start in range(0, len(ids), _BATCH):
            keys = [self._key(i) for i in ids[start : start + _BATCH]]
            for raw in self.redis.mget(keys):
                job = self._decode(raw)
                if job is not None:  # deleted since the id was read
                    yield job

    # -- reads ---------------------------------------------------------------------------------
    def get(self, job_id: str) -> JobRecord | None:
        return self._decode(self.redis.get(self._key(job_id)))

    def by_output(
        self, output_id: str, with_deleted: bool = False, kind: str | None = "avatar"
    ) -> JobRecord | None:
        job_id = self.redis.get(self._output_key(output_id))
        job = self.get(job_id.decode()) if job_id else None
        if (
            job is None
            or (job.output_deleted and not with_deleted)
            or (kind is not None and job.kind != kind)
        ):
            return None
        return job

    def list(
        self,
        states: tuple[str, ...] | None = None,
        with_deleted: bool = False,
        kind: str | None = None,
        account: str | None = None,
    ) -> list[JobRecord]:
        return [
            job
            for job in self._all()
            if (account is None or job.account == account)
            and (kind is None or job.kind == kind)
            and (not states or job.state in states)
            and (with_deleted or not job.output_deleted)
        ]

    def queued(self, account: str | None = None) -> int:
        return len(self.list(states=("queued",), with_deleted=True, account=account))

    def counts(self) -> dict[str, int]:
        counts = dict.fromkeys(STATES, 0)
        for job in self._all():
            counts[job.state] = counts.get(job.state, 0) + 1
        return counts

    # -- writes --------------------------------------------------------------------------------
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
        key, output = self._key(job.id), self._output_key(job.output_id)

        def insert(pipe) -> JobRecord:
            if pipe.exists(key) or pipe.exists(output):
                raise DuplicateJobError(f"a job {job.id} or one making {job.output_id} exists already")
            pipe.multi()
            pipe.set(key, self._encode(job))
            pipe.set(output, job.id)
            pipe.zadd(self._ids, {job.id: job.created_at})
            pipe.execute()
            return job

        return self._atomically([key, output], insert)

    def _atomically(self, keys: list[str], step: Callable[[Any], Any]) -> Any:
        """``step(pipe)`` under WATCH of ``keys``: it reads, decides, and either queues its writes
        after ``pipe.multi()`` and executes them, or returns without writing; when another client
        changed a watched key meanwhile, it runs again on what is there now. Returns its result."""
        from redis.exceptions import WatchError

        with self.redis.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(*keys)
                    return step(pipe)
                except WatchError:
                    continue

    def _change(self, job_id: str, change: Callable[[JobRecord], JobRecord | None]) -> JobRecord | None:
        """Apply ``change`` (the new record, or None to leave it) to the current record atomically;
        returns the record written, or None."""
        key = self._key(job_id)

        def apply(pipe) -> JobRecord | None:
            current = self._decode(pipe.get(key))
            new = change(current) if current is not None else None
            if new is not None:
                pipe.multi()
                pipe.set(key, self._encode(new))
                pipe.execute()
            return new

        return self._atomically([key], apply)

    def update(
        self,
        job_id: str,
        *,
        where_state: tuple[str, ...] | None = None,
        owner: str | None = None,
        expect: JobRecord | None = None,
        **fields: Any,
    ) -> bool:
        unknown = set(fields) - _FIELDS
        if unknown:
            raise ValueError(f"unknown job record fields {sorted(unknown)}")
        fields["updated_at"] = time.time()
        for flag in ("cancel_requested", "output_deleted"):
            if flag in fields:
                fields[flag] = bool(fields[flag])

        def change(job: JobRecord) -> JobRecord | None:
            if not job.matches(where_state, owner, expect):
                return None
            return dataclasses.replace(job, **fields)

        return self._change(job_id, change) is not None

    def claim(self, job_id: str, worker: str) -> JobRecord | None:
        now = time.time()

        def change(job: JobRecord) -> JobRecord | None:
            if job.state != "queued" or job.cancel_requested:
                return None
            return dataclasses.replace(
                job,
                state="running",
                worker=worker,
                attempts=job.attempts + 1,
                started_at=job.started_at if job.started_at is not None else now,
                heartbeat_at=now,
                updated_at=now,
                message=None,
            )

        return self._change(job_id, change)

    def heartbeat(self, job_id: str, worker: str) -> JobRecord | None:
        now = time.time()

        def change(job: JobRecord) -> JobRecord | None:
            if job.state != "running" or job.worker != worker:
                return None
            return dataclasses.replace(job, heartbeat_at=now)

        return self._change(job_id, change)

    def delete(self, job_id: str) -> None:
        job = self.get(job_id)
        if job is None:
            return
        self._delete(job)

    def _delete(self, job: JobRecord, finished_before: float | None = None) -> bool:
        """Remove ``job``'s keys (only while it is still purgeable, with ``finished_before``)."""
        key, output = self._key(job.id), self._output_key(job.output_id)

        def remove(pipe) -> bool:
            current = self._decode(pipe.get(key))
            if current is None or (finished_before is not None and not purgeable(current, finished_before)):
                return False
            owner = pipe.get(output)
            pipe.multi()
            pipe.delete(key)
            if owner is not None and owner.decode() == job.id:
                pipe.delete(output)
            pipe.zrem(self._ids, job.id)
            pipe.execute()
            return True

        return self._atomically([key, output], remove)

    def purge(self, finished_before: float) -> list[JobRecord]:
        gone = [job for job in self._all() if purgeable(job, finished_before)]
        return [job for job in gone if self._delete(job, finished_before)]
