"""Avatars, animations and uploads in an S3-compatible bucket (``jobs.storage_s3``), against a real
S3 endpoint on loopback (moto's server mode): two hosts that share no disk see one bucket."""

from __future__ import annotations

from pathlib import Path

import boto3
import pytest
from botocore.config import Config
from helpers import service as svc

from jobs import JobsConfig, Storage, StorageUnavailable, open_storage
from jobs.storage_s3 import MARKER, S3Storage

s3_bucket = svc.s3_bucket  # a fixture
AVATAR = "a" * 32
JOB = "b" * 32


def host(tmp_path: Path, name: str, bucket: tuple[str, str]) -> S3Storage:
    """The storage of one host: its own data dir, the shared bucket."""
    endpoint, url = bucket
    return open_storage(JobsConfig(data_dir=tmp_path / name, storage_url=url, s3_endpoint_url=endpoint))


def folder(path: Path, files: dict[str, bytes]) -> Path:
    for rel, data in files.items():
        (path / rel).parent.mkdir(parents=True, exist_ok=True)
        (path / rel).write_bytes(data)
    return path


def test_an_avatar_published_on_one_host_is_read_and_deleted_on_another(tmp_path, s3_bucket):
    worker, api = host(tmp_path, "worker", s3_bucket), host(tmp_path, "api", s3_bucket)
    assert isinstance(worker, S3Storage) and isinstance(open_storage(JobsConfig(data_dir=tmp_path)), Storage)
    files = {"avatar.json": b"{}", "gaussians.ply": b"x" * 100_000, "nets/weights.safetensors": b"w"}
    assert not api.avatar_exists(AVATAR)
    worker.publish(folder(tmp_path / "trained", files), AVATAR)
    assert not (tmp_path / "trained").exists()  # moved into the worker's cache
    with pytest.raises(FileExistsError):
        worker.publish(folder(tmp_path / "again", files), AVATAR)

    assert api.avatar_exists(AVATAR)
    local = api.avatar_dir(AVATAR)  # downloaded on first use
    assert local == tmp_path / "api" / "avatars" / AVATAR
    assert {p.relative_to(local).as_posix(): p.read_bytes() for p in local.rglob("*") if p.is_file()} == files

    api.delete_avatar(AVATAR)
    assert not local.exists() and not api.avatar_exists(AVATAR)
    # The worker's cached copy is dropped once the bucket no longer has it.
    assert (tmp_path / "worker" / "avatars" / AVATAR).is_dir()
    assert not worker.avatar_exists(AVATAR) and not (tmp_path / "worker" / "avatars" / AVATAR).exists()


def test_a_folder_without_its_marker_does_not_exist(tmp_path, s3_bucket):
    endpoint, url = s3_bucket
    storage = host(tmp_path, "api", s3_bucket)
    client = boto3.client("s3", endpoint_url=endpoint)
    # A publish cut short: files, no marker.
    client.put_object(Bucket="eva-test", Key=f"service/animations/{AVATAR}/animation.mp4", Body=b"half")
    assert not storage.animation_exists(AVATAR)
    assert not storage.animation_dir(AVATAR).exists()
    client.put_object(Bucket="eva-test", Key=f"service/animations/{AVATAR}/{MARKER}", Body=b"")
    assert storage.animation_exists(AVATAR)
    assert (storage.animation_dir(AVATAR) / "animation.mp4").read_bytes() == b"half"


def test_an_upload_travels_from_the_api_host_to_a_worker_host(tmp_path, s3_bucket):
    api, worker = host(tmp_path, "api", s3_bucket), host(tmp_path, "worker", s3_bucket)
    work = api.work_dir(JOB)
    folder(work, {"input.video": b"video bytes"})
    api.save_upload(JOB)
    assert not work.exists()  # the bucket holds it now
    fetched = worker.fetch_upload(JOB)
    assert fetched == tmp_path / "worker" / "jobs" / "work" / JOB
    assert (fetched / "input.video").read_bytes() == b"video bytes"
    folder(fetched, {"dataset/meta.json": b"{}"})  # a stage's result stays on the worker's disk
    assert worker.fetch_upload(JOB) == fetched
    worker.remove_work(JOB)
    assert not fetched.exists()
    assert not (api.fetch_upload(JOB) / "input.video").exists()  # gone from the bucket too
    with pytest.raises(FileNotFoundError, match="no upload"):
        api.save_upload("c" * 32)


def test_unsafe_keys_and_a_missing_bucket_are_refused(tmp_path, s3_bucket):
    endpoint, _ = s3_bucket
    storage = host(tmp_path, "api", s3_bucket)
    client = boto3.client("s3", endpoint_url=endpoint)
    for key in (f"service/avatars/{AVATAR}/../../escape", f"service/avatars/{AVATAR}/{MARKER}"):
        client.put_object(Bucket="eva-test", Key=key, Body=b"")
    with pytest.raises(StorageUnavailable, match="unsafe key"):
        storage.avatar_dir(AVATAR)
    assert not (tmp_path / "api" / "escape").exists()
    with pytest.raises(StorageUnavailable, match="'no-such-bucket' does not exist"):
        S3Storage(
            JobsConfig(data_dir=tmp_path / "x", storage_url="s3://no-such-bucket", s3_endpoint_url=endpoint)
        )
    closed = f"http://127.0.0.1:{svc.free_port()}"
    once = boto3.client("s3", endpoint_url=closed, config=Config(retries={"max_attempts": 1}))
    with pytest.raises(StorageUnavailable, match="unavailable"):
        S3Storage(JobsConfig(data_dir=tmp_path / "y", storage_url="s3://eva-test"), client=once)


def test_the_sweeper_removes_uploads_whose_job_ended_or_never_was(tmp_path, s3_bucket):
    import time

    from jobs import SqliteJobStore, sweep

    endpoint, url = s3_bucket
    config = JobsConfig(
        data_dir=tmp_path / "api", storage_url=url, s3_endpoint_url=endpoint, orphan_ttl_s=3600
    )
    storage, store = S3Storage(config), SqliteJobStore(tmp_path / "jobs.db")
    ended, running = store.create({}), store.create({})
    store.finish(ended.id, "failed", error="x")
    store.claim(running.id, "w")
    for job_id in (ended.id, running.id, JOB):  # JOB: no record (the API died after storing it)
        folder(storage.work_dir(job_id), {"input.video": b"v"})
        storage.save_upload(job_id)
    now = time.time()
    assert {j for j, _ in storage.remote_uploads(now)} == {ended.id, running.id, JOB}
    assert sweep(config, store, storage, now=now + 120).uploads == [ended.id]  # no record: not yet
    done = sweep(config, store, storage, now=now + 7200)
    assert done.uploads == [JOB]
    assert [j for j, _ in storage.remote_uploads(now)] == [running.id]  # a live job's upload stays
