"""Job records, storage ids, recovery of jobs whose worker died, and the pipeline's clean
failure and cancellation, in-process (huey in SQLite mode, tasks run by ``run_pending``)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time

import pytest
from helpers.service import run_job_here

from eva_engine.synth.hard import nobody_video
from jobs import InvalidIdError, JobOptions, JobQueue, JobsConfig, SqliteJobStore, Storage

HOST = socket.gethostname()


@pytest.fixture
def queue(tmp_path) -> JobQueue:
    return JobQueue(JobsConfig(data_dir=tmp_path / "data", stale_after_s=30, heartbeat_s=0.5))


def submit(queue: JobQueue, video, **options) -> str:
    job = queue.store.create(JobOptions(**options).model_dump(), filename=video.name)
    work = queue.storage.work_dir(job.id)
    work.mkdir(parents=True)
    shutil.copy(video, work / f"input{video.suffix}")
    queue.enqueue(job.id)
    return job.id


def test_records_persist_and_claims_are_exclusive(tmp_path):
    store = SqliteJobStore(tmp_path / "jobs.db")
    job = store.create({"preset": "tiny"}, filename="a.mp4")
    again = SqliteJobStore(tmp_path / "jobs.db")  # a restarted process
    assert again.get(job.id).state == "queued" and again.get(job.id).options == {"preset": "tiny"}
    assert store.claim(job.id, "w1").state == "running"
    assert again.claim(job.id, "w2") is None
    assert store.finish(job.id, "succeeded") and not store.finish(job.id, "failed")
    assert again.get(job.id).state == "succeeded" and again.get(job.id).progress == 1.0


def test_storage_refuses_path_traversal(tmp_path):
    storage = Storage(JobsConfig(data_dir=tmp_path))
    for bad in ("../../etc", "..", "a" * 31, "A" * 32, "a/b", ""):
        with pytest.raises(InvalidIdError):
            storage.avatar_dir(bad)
        with pytest.raises(InvalidIdError):
            storage.work_dir(bad)
    assert storage.avatar_dir("a" * 32).parent == tmp_path / "avatars"


def test_dead_workers_jobs_are_retried_then_failed(tmp_path):
    queue = JobQueue(JobsConfig(data_dir=tmp_path, max_attempts=2, max_worker_losses=3, stale_after_s=30))
    dead = subprocess.Popen(["true"])
    dead.wait()
    job = queue.store.create(JobOptions().model_dump())
    queue.store.claim(job.id, f"{HOST}:{dead.pid}:0000")
    queue.store.update(job.id, stage="train", completed_stage="align")
    # A live worker (this process) is left alone.
    other = queue.store.create(JobOptions().model_dump())
    queue.store.claim(other.id, f"{HOST}:{os.getpid()}:me")
    result = queue.recover(this_worker=f"{HOST}:{os.getpid()}:me")
    assert result.requeued == [job.id] and result.failed == []
    record = queue.store.get(job.id)
    assert record.state == "queued" and record.stage == "train" and record.worker_losses == 1
    assert "retrying from stage 'train'" in record.message
    assert queue.store.get(other.id).state == "running"
    # A worker that dies under the job is not the job's doing: a second death (past max_attempts)
    # sends it back again, with its upload.
    queue.store.claim(job.id, f"host-elsewhere:{dead.pid}:0000")
    queue.store.update(job.id, heartbeat_at=time.time() - 60)  # silent for longer than stale_after_s
    queue.storage.work_dir(job.id).mkdir(parents=True)
    (queue.storage.work_dir(job.id) / "input.video").write_bytes(b"v")
    assert queue.recover().requeued == [job.id]
    assert queue.store.get(job.id).attempts == 2 and (queue.storage.work_dir(job.id) / "input.video").exists()
    # The third lost worker uses up max_worker_losses: the job fails with the reason and its files go.
    queue.store.claim(job.id, f"host-elsewhere:{dead.pid}:0001")
    queue.store.update(job.id, heartbeat_at=time.time() - 60)
    result = queue.recover()
    assert result.failed == [job.id]
    record = queue.store.get(job.id)
    assert record.state == "failed" and "giving up after 3 workers stopped" in record.error
    assert not queue.storage.work_dir(job.id).exists()


def test_a_jobs_own_crashes_count_against_max_attempts_not_its_workers_deaths(tmp_path):
    queue = JobQueue(JobsConfig(data_dir=tmp_path, max_attempts=2))
    job = queue.store.create(JobOptions().model_dump())
    queue.store.claim(job.id, "w1")
    lost = queue._give_back(queue.store.get(job.id), "its worker stopped", worker_lost=True, owner="w1")
    assert lost == "requeued"
    queue.store.claim(job.id, "w2")
    # Attempt 2 of max_attempts=2, but the first was a lost worker: one crash of its own is left.
    assert queue._give_back(queue.store.get(job.id), "its process was killed", owner="w2") == "requeued"
    queue.store.claim(job.id, "w1")
    queue.store.claim(job.id, "w1")
    assert queue._give_back(queue.store.get(job.id), "its process was killed", owner="w1") == "failed"
    assert "2 time(s); giving up after 2 attempts" in queue.store.get(job.id).error


def test_a_video_without_a_person_fails_cleanly(queue, tmp_path):
    job_id = submit(queue, nobody_video(tmp_path / "nobody.mp4"), preset="tiny")
    assert queue.run_pending() >= 1
    job = queue.store.get(job_id)
    assert job.state == "failed" and "no person" in job.error and "stage preprocess" in job.error
    assert str(queue.storage.work_dir(job_id)) not in job.error
    assert "frames of the uploaded video: the video must show one person" in job.error  # its colon kept
    assert not queue.storage.work_dir(job_id).exists() and not queue.storage.avatar_exists(job.output_id)


def test_the_job_decodes_the_upload_as_the_probe_approved_it(queue, tmp_path, monkeypatch, anny_model):
    """The job opens the upload with the demuxer the probe chose from its bytes, under the
    probe's size limit, whatever the user called the file (the API stores it as input.video)."""
    import eva_engine.align as align

    configs = []
    real = align.preprocess_video

    def spy(video, out, config, **kwargs):
        configs.append(config)
        return real(video, out, config, **kwargs)

    monkeypatch.setattr(align, "preprocess_video", spy)
    job_id = submit(queue, nobody_video(tmp_path / "nobody.mp4"), preset="tiny")
    work = queue.storage.work_dir(job_id)
    (work / "input.mp4").rename(work / "input.video")
    assert run_job_here(queue, job_id, anny_model) == "failed"  # no person: decoded all the same
    assert "no person" in queue.store.get(job_id).error
    [config] = configs
    assert config.demuxer == "mov" and config.max_video_side == queue.config.max_video_side


def test_a_job_on_a_full_disk_goes_back_with_its_upload(queue, tmp_path, monkeypatch, anny_model):
    """A full disk is the server's state, not the job's fault: the attempt stops without ending
    the job or removing its upload; its process exits with EXIT_DISK_FULL, which the worker
    reads as a reason to give the job back (``exit_reason``)."""
    import errno

    import eva_engine.align as align
    from jobs.disk import EXIT_DISK_FULL, DiskFull
    from jobs.runner import exit_reason

    def no_space(video, out, config, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(align, "preprocess_video", no_space)
    job_id = submit(queue, nobody_video(tmp_path / "v.mp4"), preset="tiny")
    with pytest.raises(DiskFull):
        run_job_here(queue, job_id, anny_model)
    job = queue.store.get(job_id)
    assert job.state == "running" and job.error is None  # the worker decides, as after a crash
    assert (queue.storage.work_dir(job_id) / "input.mp4").is_file()
    assert exit_reason(EXIT_DISK_FULL, queue.config) == "the server's disk was full"


def test_cancel_a_running_job(queue, tmp_path, monkeypatch):
    video = nobody_video(tmp_path / "long.mp4", frames=60)
    job_id = submit(queue, video, preset="tiny")
    claim, asked = queue.store.claim, []

    def claim_then_cancel(job_id: str, worker: str):
        # The cancel comes the moment the worker owns the job (before its process starts), not
        # after polling for a "running" state that a fast job may leave within one poll.
        job = claim(job_id, worker)
        if job is not None:
            asked.append(queue.cancel(job).cancel_requested)
        return job

    monkeypatch.setattr(queue.store, "claim", claim_then_cancel)
    queue.run_pending()
    assert asked == [True]
    job = queue.store.get(job_id)
    assert job.state == "cancelled" and job.error is None
    assert not queue.storage.work_dir(job_id).exists()


def test_job_methods_are_the_engines():
    import typing

    from eva_engine.train import METHODS
    from jobs.options import Method

    assert typing.get_args(Method) == tuple(METHODS)
    assert JobOptions(method="eva").method == "eva"


def test_a_jobs_training_is_its_preset_under_the_services_caps():
    """The job's TrainConfig: the preset with the job's overrides and method, at most the
    service's Gaussians, and every Gaussian's standard deviation under its bound; no bound leaves
    the preset's."""
    from eva_engine.train import preset

    options = JobOptions(preset="tiny", iterations=7, method="eva")
    config = options.train_config(max_gaussians=5000, max_std_m=0.1)
    assert config.iterations == 7 and config.strategy.max_gaussians <= 5000
    assert config.avatar.max_scale == (0.1, 0.1, 0.1)
    assert options.train_config(5000).avatar.max_scale == preset("tiny").avatar.max_scale


def test_a_job_keeps_frames_out_for_its_quality_report():
    """The job's preprocessing: its own bounds and fit, and about one frame in ten held out of the
    frames it will use (the video's, capped at max_frames)."""
    options = JobOptions(max_frames=120, max_size=256, fit_scale=0.5)
    config = options.preprocess_config(300)
    assert (config.max_frames, config.max_size, config.test_every) == (120, 256, 10)
    assert config.fitting == options.fit_config()
    assert options.preprocess_config(None).test_every == 10  # unknown length: max_frames
    assert options.preprocess_config(20).test_every == 5  # 4 held out
    assert options.preprocess_config(1).test_every == 0  # nothing to spare


def test_face_closeups_are_one_job_option():
    """Off by default: no close-ups cut, none trained on, the preset's classic rasterizer (its
    0.1 px² dilation). On: both, and the avatar rasterized antialiased with Mip-Splatting's 2D
    filter."""
    off = JobOptions(preset="tiny")
    assert off.preprocess_config(60).face_crops is None
    assert off.train_config(5000).face_view.weight == 0
    assert (off.train_config(5000).avatar.rasterize_mode, off.train_config(5000).avatar.eps2d) == (
        "classic",
        0.1,
    )
    on = JobOptions(preset="tiny", face_closeups=True)
    assert on.preprocess_config(60).face_crops is not None
    assert on.train_config(5000).face_view.weight == 1.0
    assert (on.train_config(5000).avatar.rasterize_mode, on.train_config(5000).avatar.eps2d) == (
        "antialiased",
        0.1,
    )
