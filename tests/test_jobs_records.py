"""The job records' contract (``jobs.store.JobStore``), the same tests on both backends: SQLite on
one host and Redis (a real redis-server) for the API and workers on several."""

from __future__ import annotations

import json
import sqlite3
import threading
import time

import pytest
from helpers import service as svc

from jobs import JobsConfig, SqliteJobStore, open_store
from jobs.store_redis import DuplicateJobError, RedisJobStore

redis_url = svc.redis_url  # a fixture


@pytest.fixture(params=["sqlite", "redis"])
def stores(request, tmp_path):
    """A function that opens the same records again (as another process or host would)."""
    if request.param == "sqlite":
        return lambda: SqliteJobStore(tmp_path / "jobs.db")
    url = request.getfixturevalue("redis_url")
    return lambda: RedisJobStore(url)


def test_backends_are_chosen_by_the_configuration(tmp_path, redis_url):
    assert isinstance(open_store(JobsConfig(data_dir=tmp_path)), SqliteJobStore)
    store = open_store(JobsConfig(data_dir=tmp_path, records_url=redis_url, queue_name="studio"))
    assert isinstance(store, RedisJobStore) and store.prefix == "studio:records"
    with pytest.raises(ValueError, match="records URL"):
        JobsConfig(data_dir=tmp_path, records_url="sqlite:///x.db")
    with pytest.raises(ValueError, match="s3://bucket"):
        JobsConfig(data_dir=tmp_path, storage_url="s3://")


def test_records_persist_and_claims_are_exclusive(stores):
    store, again = stores(), stores()
    job = store.create({"preset": "tiny"}, filename="a.mp4", account="ann")
    got = again.get(job.id)
    assert got == job and got.options == {"preset": "tiny"} and got.message == "waiting for a worker"
    claimed = store.claim(job.id, "w1")
    assert claimed.state == "running" and claimed.worker == "w1" and claimed.attempts == 1
    assert claimed.started_at is not None and claimed.heartbeat_at is not None and claimed.message is None
    assert again.claim(job.id, "w2") is None
    assert store.finish(job.id, "succeeded", message="avatar ready") and not store.finish(job.id, "failed")
    done = again.get(job.id)
    assert (done.state, done.progress, done.eta_s, done.message) == ("succeeded", 1.0, 0.0, "avatar ready")
    assert again.get("f" * 32) is None


def test_one_claim_wins_among_threads(stores):
    job = stores().create({})
    winners, start = [], threading.Barrier(8)

    def claim(name: str) -> None:
        store = stores()
        start.wait()
        if store.claim(job.id, name) is not None:
            winners.append(name)

    threads = [threading.Thread(target=claim, args=(f"w{i}",)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(winners) == 1 and stores().get(job.id).worker == winners[0]


def test_conditional_writes(stores):
    store = stores()
    job = store.create({})
    assert not store.update(job.id, where_state=("running",), message="no")
    assert store.update(job.id, where_state=("queued",), cancel_requested=1)
    assert store.get(job.id).cancel_requested is True
    assert store.claim(job.id, "w1") is None  # a cancelled queued job is never claimed
    assert store.update(job.id, cancel_requested=0)
    running = store.claim(job.id, "w1")
    assert not store.update(job.id, owner="w2", progress=0.5)
    assert store.update(job.id, owner="w1", progress=0.5, stage="align")
    # expect=: only while the record is exactly as judged (here its heartbeat moved on).
    time.sleep(0.01)
    beat = store.heartbeat(job.id, "w1")
    assert beat.heartbeat_at > running.heartbeat_at and store.heartbeat(job.id, "w2") is None
    assert not store.update(job.id, expect=running, state="queued")
    assert store.update(job.id, expect=beat, state="queued", worker=None)
    again = store.get(job.id)
    assert (again.state, again.worker, again.stage, again.progress) == ("queued", None, "align", 0.5)
    assert store.claim(job.id, "w3").attempts == 2
    assert store.finish(job.id, "failed", error="broken", owner="w3")
    assert store.get(job.id).eta_s is None and store.get(job.id).error == "broken"
    with pytest.raises(ValueError, match="terminal"):
        store.finish(job.id, "running")


def test_lookups_listings_and_counts(stores):
    store = stores()
    a = store.create({}, account="ann")
    b = store.create({"avatar_id": a.output_id}, kind="animation", account="bob")
    c = store.create({}, account="ann")
    with pytest.raises(ValueError, match="kind"):
        store.create({}, kind="not a name")  # which kinds exist is jobs.kinds'; a record needs a name
    assert store.by_output(a.output_id).id == a.id
    assert store.by_output(b.output_id) is None and store.by_output(b.output_id, kind="animation").id == b.id
    assert store.by_output(b.output_id, kind=None).id == b.id
    assert [j.id for j in store.list()] == [a.id, b.id, c.id]  # oldest first
    assert [j.id for j in store.list(account="ann")] == [a.id, c.id]
    assert [j.id for j in store.list(kind="animation")] == [b.id]
    store.claim(c.id, "w1")
    assert [j.id for j in store.list(states=("running",))] == [c.id]
    assert store.queued() == 2 and store.queued("ann") == 1 and store.queued("eve") == 0
    assert store.counts() == {"queued": 2, "running": 1, "succeeded": 0, "failed": 0, "cancelled": 0}
    store.finish(c.id, "succeeded")
    store.update(c.id, output_deleted=1)
    assert store.by_output(c.output_id) is None and store.by_output(c.output_id, with_deleted=True).id == c.id
    assert [j.id for j in store.list(account="ann")] == [a.id]
    assert [j.id for j in store.list(account="ann", with_deleted=True)] == [a.id, c.id]
    store.delete(b.id)
    assert store.get(b.id) is None and store.by_output(b.output_id, kind=None) is None
    assert [j.id for j in store.list()] == [a.id]


def test_purge_takes_only_what_left_nothing_to_serve(stores):
    store = stores()
    kept = store.create({})  # succeeded, its avatar still served
    failed, cancelled, deleted, recent = (store.create({}) for _ in range(4))
    for job in (kept, deleted):
        store.claim(job.id, "w")
        store.finish(job.id, "succeeded")
    store.update(deleted.id, output_deleted=1)
    store.finish(failed.id, "failed", error="x")
    store.finish(cancelled.id, "cancelled")
    cutoff = time.time() + 1
    store.finish(recent.id, "failed", error="later")
    store.update(recent.id, finished_at=cutoff + 10)
    gone = store.purge(finished_before=cutoff)
    assert sorted(j.id for j in gone) == sorted([failed.id, cancelled.id, deleted.id])
    assert {j.id for j in store.list(with_deleted=True)} == {kept.id, recent.id}


def test_redis_refuses_a_second_job_for_one_output(redis_url):
    store = RedisJobStore(redis_url)
    job = store.create({})
    with pytest.raises(DuplicateJobError):
        store.create({}, output_id=job.output_id)
    with pytest.raises(DuplicateJobError):
        store.create({}, job_id=job.id)
    with pytest.raises(ValueError, match="unknown job record fields"):
        store.update(job.id, colour="red")
    # Two services on one Redis keep apart by their queue names.
    assert RedisJobStore(redis_url, prefix="other:records").get(job.id) is None


def test_records_written_before_the_output_rename_are_read(tmp_path, redis_url):
    """A jobs.db of the first release (``avatar_id``, ``avatar_deleted``, none of the later
    columns) is migrated when opened; a Redis record of that time is read as it is."""
    path, job_id, output_id = tmp_path / "jobs.db", "a" * 32, "b" * 32
    with sqlite3.connect(path) as db:
        db.execute(
            "CREATE TABLE jobs (id TEXT PRIMARY KEY, avatar_id TEXT NOT NULL UNIQUE, state TEXT NOT NULL, "
            "stage TEXT, completed_stage TEXT, progress REAL NOT NULL DEFAULT 0, eta_s REAL, message TEXT, "
            "error TEXT, options TEXT NOT NULL, filename TEXT, attempts INTEGER NOT NULL DEFAULT 0, "
            "worker TEXT, cancel_requested INTEGER NOT NULL DEFAULT 0, "
            "avatar_deleted INTEGER NOT NULL DEFAULT 0, created_at REAL NOT NULL, started_at REAL, "
            "finished_at REAL, updated_at REAL NOT NULL, heartbeat_at REAL)"
        )
        db.execute(
            "INSERT INTO jobs (id, avatar_id, state, options, avatar_deleted, created_at, updated_at) "
            "VALUES (?, ?, 'succeeded', '{}', 1, 1.0, 2.0)",
            (job_id, output_id),
        )
    store = SqliteJobStore(path)
    job = store.get(job_id)
    assert (job.output_id, job.output_deleted, job.kind, job.worker_losses) == (output_id, True, "avatar", 0)
    assert store.by_output(output_id) is None and store.by_output(output_id, with_deleted=True).id == job_id
    assert store.create({}).output_id != output_id  # the table takes new records
    assert SqliteJobStore(path).get(job_id) == job  # opened again: nothing left to migrate

    redis = RedisJobStore(redis_url)
    old = {k: v for k, v in vars(job).items() if k not in ("output_id", "output_deleted")}
    redis.redis.set(redis._key(job_id), json.dumps({**old, "avatar_id": output_id, "avatar_deleted": 1}))
    assert redis.get(job_id) == job
