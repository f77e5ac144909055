"""One job, one owner: every write of a worker is conditional on still owning the job, recovery
judges a same-host worker by its process before its heartbeat and changes a job only if it is
still as judged, the heartbeat survives store errors, and two attempts racing one job end with
one result and no lost files. Also: queued jobs whose message was lost, the sweeper, each job's
memory and time limits (in its own process), and job records refused on a network file system."""

from __future__ import annotations

import os
import shutil
import socket
import sqlite3
import subprocess
import threading
import time

import pytest
from helpers import service as svc
from helpers.service import FAST_OPTIONS, gradient_video

from eva_engine.avatar import read_avatar_meta
from eva_engine.progress import ProgressEvent
from jobs import JobLost, JobOptions, JobQueue, JobRun, JobsConfig, JobStoreError, SqliteJobStore, sweep
from jobs import store as store_module
from jobs.avatar import AVATAR
from jobs.pipeline import Reporter
from jobs.queue import RUN_TASK
from jobs.runner import JobRunner, _pid_namespace, _start_time

signer_video = svc.signer_video  # a fixture
HOST = socket.gethostname()
OPTIONS = JobOptions.model_validate(FAST_OPTIONS)


def local_id(pid: int, start: str | None = None, token: str = "t") -> str:
    return f"{HOST}:{_pid_namespace()}:{pid}:{start if start is not None else _start_time(pid)}:{token}"


def submit(queue: JobQueue, video, options: JobOptions = OPTIONS, enqueue: bool = True) -> str:
    job = queue.store.create(options.model_dump(), filename=video.name)
    work = queue.storage.work_dir(job.id)
    work.mkdir(parents=True)
    shutil.copy(video, work / f"input{video.suffix}")
    if enqueue:
        queue.enqueue(job.id)
    return job.id


@pytest.fixture
def queue(tmp_path) -> JobQueue:
    return JobQueue(JobsConfig(data_dir=tmp_path / "data", stale_after_s=30, heartbeat_s=0.2))


@pytest.fixture
def sleeper():
    proc = subprocess.Popen(["sleep", "60"])
    yield proc
    proc.kill()
    proc.wait()


def test_a_worker_that_lost_its_job_cannot_write_to_it(queue):
    store = queue.store
    job = store.create(OPTIONS.model_dump())
    a = store.claim(job.id, "elsewhere:1:10:100:a")
    store.update(job.id, heartbeat_at=time.time() - 60)  # silent past stale_after_s, on another host
    assert queue.recover().requeued == [job.id]
    b = store.claim(job.id, local_id(os.getpid(), token="b"))
    assert b is not None and b.attempts == 2
    # A comes back: none of its writes land.
    assert not store.update(job.id, owner=a.worker, progress=0.9)
    assert not store.finish(job.id, "succeeded", owner=a.worker)
    assert store.heartbeat(job.id, a.worker) is None
    report = Reporter(store, a, a.worker, AVATAR.stage_spans)
    with pytest.raises(JobLost):
        report(ProgressEvent("train", 1, 2), force=True)
    with pytest.raises(JobLost):
        report.completed("train")
    current = store.get(job.id)
    assert current.state == "running" and current.worker == b.worker and current.progress == 0.0
    owner = Reporter(store, b, b.worker, AVATAR.stage_spans)
    owner(ProgressEvent("train", 1, 2), force=True)  # the owner's do
    assert store.finish(job.id, "succeeded", owner=b.worker)


def test_recovery_checks_a_local_process_before_its_heartbeat(queue, sleeper):
    store, old = queue.store, time.time() - 3600
    dead = subprocess.Popen(["true"])
    dead.wait()
    cases = {
        "alive, silent for an hour": (local_id(sleeper.pid), old, False),  # fitting can be silent
        "dead, fresh heartbeat": (local_id(dead.pid, start="1"), time.time(), True),
        "pid reused by another process": (local_id(sleeper.pid, start="1"), time.time(), True),
        "other host, silent": ("elsewhere:1:10:100:x", old, True),
        "other host, fresh": ("elsewhere:1:10:100:y", time.time(), False),
        "other pid namespace, fresh": (f"{HOST}:999:{dead.pid}:1:z", time.time(), False),
    }
    ids = {}
    for name, (worker, beat) in ((n, (w, b)) for n, (w, b, _) in cases.items()):
        job = store.create(OPTIONS.model_dump())
        store.claim(job.id, worker)
        store.update(job.id, heartbeat_at=beat)
        ids[name] = job.id
    requeued = set(queue.recover().requeued)
    for name, (_, _, gone) in cases.items():
        assert (ids[name] in requeued) == gone, name


def test_recovery_changes_a_job_only_as_it_judged_it(queue):
    store = queue.store
    job = store.create(OPTIONS.model_dump())
    store.claim(job.id, "elsewhere:1:10:100:a")
    store.update(job.id, heartbeat_at=time.time() - 60)
    judged = store.get(job.id)
    store.heartbeat(job.id, judged.worker)  # the worker speaks up meanwhile
    assert queue._give_back(judged, "its worker stopped", expect=judged) is None
    assert store.get(job.id).state == "running"
    # Two recoveries of the same snapshot: one wins, one message is sent.
    store.update(job.id, heartbeat_at=time.time() - 60)
    judged = store.get(job.id)
    outcomes = [queue._give_back(judged, "its worker stopped", expect=judged) for _ in range(2)]
    assert outcomes == ["requeued", None]
    assert [t.args[0] for t in queue.huey.pending() if t.name == RUN_TASK] == [job.id]


def test_the_heartbeat_survives_store_errors(queue, monkeypatch, caplog):
    store = queue.store
    job = store.create(OPTIONS.model_dump())
    runner = JobRunner(queue.config, store, queue.storage)
    claimed = store.claim(job.id, runner.worker)
    store.update(job.id, heartbeat_at=0.0)
    real, failures = store.heartbeat, []

    def flaky(job_id, worker):
        if len(failures) < 3:
            failures.append(1)
            raise sqlite3.OperationalError("database is locked")
        return real(job_id, worker)

    monkeypatch.setattr(store, "heartbeat", flaky)
    child = subprocess.Popen(["sleep", "2"])
    assert runner._watch(claimed, child) is None  # the child ended; the watch was not stopped by errors
    assert len(failures) == 3 and store.get(job.id).heartbeat_at > time.time() - 5
    assert "heartbeat failed; retrying" in caplog.text


@pytest.mark.slow
def test_two_attempts_racing_one_job_end_with_one_result(queue, signer_video, anny_model):
    """A's heartbeat went silent (another host, no beat for longer than stale_after_s): recovery
    gives the job to B while A still runs it. A stops at its next report without writing; B's
    result is the job's; nothing is left behind."""
    store, storage = queue.store, queue.storage
    job_id = submit(queue, signer_video, enqueue=False)
    a_job = store.claim(job_id, "elsewhere:1:10:100:a")
    a = JobRun(queue.config, store, storage, a_job, a_job.worker, AVATAR)
    a.add_body_model(anny_model)
    # A is parked inside its preprocess stage (where it asks for the body model) while recovery
    # hands the job to B: waiting on events, not polling for a stage that may last 0.2 s.
    a_parked, a_resume = threading.Event(), threading.Event()
    a_model = a.body_model

    def parked_body_model(name: str):
        a_parked.set()
        assert a_resume.wait(120), "A was never resumed"
        return a_model(name)

    a.body_model = parked_body_model
    outcome: dict = {}
    runner_a = threading.Thread(target=lambda: outcome.__setitem__("a", a.execute()))
    runner_a.start()
    assert a_parked.wait(120), "A never reached its preprocess stage"
    assert store.get(job_id).stage == "preprocess"
    store.update(job_id, heartbeat_at=time.time() - 60)
    assert queue.recover().requeued == [job_id]
    b_job = store.claim(job_id, local_id(os.getpid(), token="b"))
    a_resume.set()  # A runs on: its next report finds the job gone and stops without writing
    runner_a.join(300)
    assert not runner_a.is_alive()
    b = JobRun(queue.config, store, storage, b_job, b_job.worker, AVATAR)
    b.add_body_model(anny_model)
    outcome["b"] = b.execute()
    assert outcome == {"a": None, "b": "succeeded"}, outcome
    final = store.get(job_id)
    assert final.state == "succeeded" and final.worker == b_job.worker and final.attempts == 2
    assert sorted(p.name for p in queue.config.avatars_dir.iterdir()) == [final.output_id]
    assert not storage.work_dir(job_id).exists()
    assert not [p for p in queue.config.data_dir.rglob("*") if ".partial" in p.name]


def test_a_queued_job_whose_message_was_lost_is_sent_again(queue, signer_video):
    job_id = submit(queue, signer_video, enqueue=False)  # the API died between create and enqueue
    fresh = submit(queue, signer_video)
    assert queue.recover().resent == []  # not yet stale
    store = queue.store
    store.update(job_id, created_at=time.time() - 3600)
    store.update(fresh, enqueued_at=time.time() - 3600)
    result = queue.recover()
    assert result.resent == [job_id]  # the fresh job's message is still in the queue
    pending = [t.args[0] for t in queue.huey.pending() if t.name == RUN_TASK]
    assert sorted(pending) == sorted([fresh, job_id])
    assert queue.recover().resent == []  # sent once, not on every pass


def test_the_sweeper_removes_what_crashes_leave(queue, signer_video):
    store, storage, config = queue.store, queue.storage, queue.config
    old = time.time() - 2 * config.orphan_ttl_s

    def aged(path):
        os.utime(path, (old, old))
        for child in path.iterdir():
            os.utime(child, (old, old))
        return path

    orphan = config.work_dir / ("a" * 32)
    orphan.mkdir()
    (orphan / "input.mp4").write_bytes(b"x")
    aged(orphan)
    uploading = config.work_dir / ("b" * 32)  # an upload in progress: recent, kept
    uploading.mkdir()
    done = store.create(OPTIONS.model_dump())
    store.finish(done.id, "failed", error="x")
    store.update(done.id, finished_at=time.time() - (config.keep_records_days + 1) * 86400)
    leftover = storage.work_dir(done.id)
    leftover.mkdir()
    aged(leftover)
    trash = config.avatars_dir / ".deleted-xyz"
    trash.mkdir()
    aged(trash)
    stray = config.avatars_dir / done.output_id
    stray.mkdir()
    aged(stray)
    live = submit(queue, signer_video)
    aged(storage.work_dir(live))  # queued for long, but its job is alive: kept
    kept = store.create(OPTIONS.model_dump())
    store.finish(kept.id, "failed", error="recent")
    # Animations: a deletion's leftovers, one whose job was cancelled, one whose job succeeded.
    animation_trash = config.animations_dir / ".deleted-abc"
    animation_trash.mkdir()
    aged(animation_trash)
    cancelled = store.create({"avatar_id": kept.output_id}, kind="animation")
    store.finish(cancelled.id, "cancelled")
    stray_animation = config.animations_dir / cancelled.output_id
    stray_animation.mkdir()
    aged(stray_animation)
    made = store.create({"avatar_id": kept.output_id}, kind="animation")
    store.update(made.id, state="succeeded")
    published = config.animations_dir / made.output_id
    published.mkdir()
    aged(published)
    # Finished results with no record at all (a backup restored beside a fresh job store):
    # moved to the quarantine, whole, never removed.
    unknown_avatar = config.avatars_dir / ("c" * 32)
    unknown_avatar.mkdir()
    (unknown_avatar / "avatar.json").write_text("{}")
    aged(unknown_avatar)
    unknown_animation = config.animations_dir / ("d" * 32)
    unknown_animation.mkdir()
    (unknown_animation / "animation.mp4").write_bytes(b"mp4")
    aged(unknown_animation)
    swept = sweep(config, store, storage)
    assert sorted(swept.folders) == sorted([orphan, leftover, trash, stray, animation_trash, stray_animation])
    assert swept.quarantined == [
        config.quarantine_dir / "avatars" / ("c" * 32),
        config.quarantine_dir / "animations" / ("d" * 32),
    ]
    assert not unknown_avatar.exists() and (swept.quarantined[0] / "avatar.json").read_text() == "{}"
    assert (swept.quarantined[1] / "animation.mp4").read_bytes() == b"mp4"
    assert sweep(config, store, storage).quarantined == []  # and left there
    assert swept.quarantined[0].exists() and swept.quarantined[1].exists()
    assert published.exists()
    assert swept.records == [done.id] and store.get(done.id) is None and store.get(kept.id) is not None
    assert uploading.exists() and storage.work_dir(live).exists()


@pytest.mark.slow
def test_a_job_over_its_memory_limit_fails_alone_with_the_reason(tmp_path, signer_video):
    """Each job runs in its own process under ``job_memory_mb``: the one that needs more fails with
    the reason; the worker (this process) and the next job are unaffected."""
    data = tmp_path / "data"
    config = JobsConfig(data_dir=data, job_memory_mb=2600, max_frame_pixels=10**9, max_attempts=1)
    queue = JobQueue(config)
    big = gradient_video(tmp_path / "big.mp4", frames=60, side=2048)  # 60 x 12 MB decoded, then stacked
    greedy = submit(queue, big, JobOptions(preset="tiny", max_frames=60, max_size=2048))
    small = submit(queue, signer_video)
    queue.run_pending()
    failed, done = queue.store.get(greedy), queue.store.get(small)
    assert failed.state == "failed" and "ran out of memory" in failed.error, failed
    assert "2600 MB" in failed.error
    assert done.state == "succeeded", done
    info = read_avatar_meta(queue.storage.avatar_dir(done.output_id))
    assert info.train_config["strategy"]["max_gaussians"] == config.max_gaussians  # the service's cap


def test_a_job_over_its_time_limit_is_stopped(tmp_path, signer_video):
    queue = JobQueue(JobsConfig(data_dir=tmp_path / "data", job_timeout_s=1.0, heartbeat_s=0.2))
    job_id = submit(queue, signer_video)
    queue.run_pending()
    job = queue.store.get(job_id)
    assert job.state == "failed" and "longer than its limit" in job.error, job
    assert not queue.storage.work_dir(job_id).exists()


def test_job_records_refuse_a_network_file_system(tmp_path, monkeypatch):
    assert store_module.filesystem_type(tmp_path) not in (None, "nfs")  # the real type of this disk
    monkeypatch.setattr(store_module, "filesystem_type", lambda path: "nfs4")
    with pytest.raises(JobStoreError, match="local disk"):
        SqliteJobStore(tmp_path / "jobs.db")
