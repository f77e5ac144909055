"""Real worker processes: one killed (SIGKILL) mid-job and restarted finishes the job from its
last completed stage (SQLite mode); a worker that goes silent is not raced by another; a job's
process killed mid-job costs only that job an attempt; two workers sharing a real redis-server
(Redis mode)."""

from __future__ import annotations

import os
import signal
import time

import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.service import (
    EVA,
    FAST_OPTIONS,
    finish_real_and_nobody,
    freeze_in_stage,
    log_tail,
    start_process,
    start_worker,
    stop,
    wait_for,
)

from eva_engine.synth.hard import nobody_video
from jobs import JobsConfig
from service.app import create_app
from service.settings import ServiceSettings

pytestmark = pytest.mark.slow
signer_video = svc.signer_video  # a fixture
redis_url = svc.redis_url  # a fixture


def api(data_dir, queue_url=None) -> TestClient:
    jobs = JobsConfig(data_dir=data_dir, queue_url=queue_url)
    return TestClient(
        create_app(ServiceSettings(jobs=jobs, preload_body_models=())), base_url="http://127.0.0.1"
    )


def upload(client, video, **options) -> dict:
    with open(video, "rb") as f:
        res = client.post("/avatars", files={"video": (video.name, f, "video/mp4")}, data=options)
    assert res.status_code == 202, res.text
    return res.json()


def test_a_killed_worker_is_replaced_and_the_job_resumes(tmp_path, signer_video):
    data, log = tmp_path / "data", tmp_path / "worker.log"
    options = {**FAST_OPTIONS, "iterations": "40"}  # a training stage long enough to kill it in
    with api(data) as client:
        ids = upload(client, signer_video, **options)
        worker = start_worker(data, log)
        try:
            freeze_in_stage(client, ids["job_id"], "train", others=(worker.pid,))
            worker.send_signal(signal.SIGKILL)  # its job's process dies with it
            worker.wait()
            job = client.get(f"/jobs/{ids['job_id']}").json()
            assert job["state"] == "running"  # nobody has noticed yet
            worker = start_worker(data, log)

            def finished():
                j = client.get(f"/jobs/{ids['job_id']}").json()
                return j["state"] in ("succeeded", "failed", "cancelled") and j

            job = wait_for(finished, 400, "the retried job")
        finally:
            stop(worker)
        assert job["state"] == "succeeded", (job, log_tail(log))
        assert job["attempts"] == 2 and job["progress"] == 1.0
        assert f"requeued ['{ids['job_id']}']" in log.read_text()  # by the new worker, at start
        assert client.get(f"/avatars/{ids['avatar_id']}").json()["status"] == "ready"
        res = client.post(f"/avatars/{ids['avatar_id']}/render", json={"width": 64, "height": 64})
        assert res.status_code == 200 and res.content[:4] == b"\x89PNG"
    assert not (data / "jobs" / "work" / ids["job_id"]).exists()
    assert sorted(p.name for p in (data / "avatars").iterdir()) == [ids["avatar_id"]]


def finished(client, job_id):
    j = client.get(f"/jobs/{job_id}").json()
    return j["state"] in ("succeeded", "failed", "cancelled") and j


def test_a_silent_worker_is_not_raced_by_another(tmp_path, signer_video):
    """Worker A and its job's process stop answering (SIGSTOP) for longer than stale_after: a worker
    B that starts meanwhile sees A's process alive on this host and leaves the job alone (it used
    to take the stale job and run it beside A, both writing the same folders)."""
    data, logs = tmp_path / "data", [tmp_path / "a.log", tmp_path / "b.log"]
    with api(data) as client:
        ids = upload(client, signer_video, **{**FAST_OPTIONS, "iterations": "40"})
        a = start_worker(data, logs[0], stale_after=2)
        b = None
        try:
            paused = freeze_in_stage(client, ids["job_id"], "train", others=(a.pid,))
            time.sleep(4)  # silent for twice stale_after
            b = start_worker(data, logs[1], stale_after=2)
            wait_for(lambda: "recovered" in logs[1].read_text(), 120, "worker B to start")
            time.sleep(2)
            for pid in paused:
                os.kill(pid, signal.SIGCONT)
            job = wait_for(lambda: finished(client, ids["job_id"]), 400, "the job")
        finally:
            for w in (a, b):
                if w is not None:
                    stop(w)
        text = "\n".join(log_tail(log, 20000) for log in logs)
        assert job["state"] == "succeeded" and job["attempts"] == 1, (job, text)
        assert f"job {ids['job_id']}: attempt" not in logs[1].read_text(), text
    assert sorted(p.name for p in (data / "avatars").iterdir()) == [ids["avatar_id"]]


def test_a_killed_job_process_costs_only_that_job_an_attempt(tmp_path, signer_video):
    """The kernel's OOM killer SIGKILLs the process that runs a job, not the worker: the worker
    records why, retries that job, and its other job runs on undisturbed."""
    data, log = tmp_path / "data", tmp_path / "worker.log"
    with api(data) as client:
        args = [EVA, "worker", "--data-dir", str(data), "--threads", "1", "--workers", "2"]
        worker = start_process(args, log)
        try:
            victim = upload(client, signer_video, **{**FAST_OPTIONS, "iterations": "40"})
            other = upload(client, signer_video, **FAST_OPTIONS)
            for pid in freeze_in_stage(client, victim["job_id"], "train"):
                os.kill(pid, signal.SIGKILL)
            first = wait_for(lambda: finished(client, victim["job_id"]), 400, "the killed job")
            second = wait_for(lambda: finished(client, other["job_id"]), 400, "the other job")
            assert worker.poll() is None  # the worker lived through it
        finally:
            stop(worker)
        text = log_tail(log, 20000)
        assert first["state"] == "succeeded" and first["attempts"] == 2, (first, text)
        assert second["state"] == "succeeded" and second["attempts"] == 1, (second, text)
        assert "the job's process was killed (SIGKILL; out of memory?" in text


def test_redis_mode_with_two_workers(tmp_path, signer_video, redis_url):
    data = tmp_path / "data"
    logs = [tmp_path / "w1.log", tmp_path / "w2.log"]
    with api(data, redis_url) as client:
        assert client.get("/healthz").json()["queue"] == "redis"
        workers = [start_worker(data, log, queue_url=redis_url) for log in logs]
        try:
            real = upload(client, signer_video, **FAST_OPTIONS)
            nobody = upload(client, nobody_video(tmp_path / "nobody.mp4"), preset="tiny")
        except BaseException:
            for w in workers:
                stop(w)
            raise
        # Each job ran exactly once, on one of the two workers; both workers were consuming.
        finish_real_and_nobody(client, workers, logs, real["job_id"], nobody["job_id"])
        res = client.post(f"/avatars/{real['avatar_id']}/render", json={"width": 64, "height": 64})
        assert res.status_code == 200
