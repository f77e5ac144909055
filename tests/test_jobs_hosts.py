"""Workers on several hosts: API hosts and worker hosts that share no disk, only a Redis (queue and
job records) and an S3-compatible bucket (avatars and uploads). Each "host" is a data dir of its
own; the workers are real ``eva worker`` processes, the bucket a real S3 endpoint (moto's server)."""

from __future__ import annotations

from pathlib import Path

import boto3
import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.service import FAST_OPTIONS, finish_real_and_nobody, start_worker, stop

from eva_engine.synth.hard import nobody_video
from jobs import JobsConfig
from service.app import create_app
from service.settings import ServiceSettings

pytestmark = pytest.mark.slow
signer_video = svc.signer_video  # fixtures
redis_url = svc.redis_url
s3_bucket = svc.s3_bucket


def api_host(data_dir: Path, redis: str, bucket: tuple[str, str]) -> TestClient:
    endpoint, url = bucket
    jobs = JobsConfig(
        data_dir=data_dir, queue_url=redis, records_url=redis, storage_url=url, s3_endpoint_url=endpoint
    )
    app = create_app(ServiceSettings(jobs=jobs, preload_body_models=()))
    return TestClient(app, base_url="http://127.0.0.1")


def files_under(path: Path) -> set[str]:
    return (
        {p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file()} if path.exists() else set()
    )


def test_jobs_cross_hosts_that_share_only_redis_and_a_bucket(
    tmp_path, signer_video, redis_url, s3_bucket, monkeypatch
):
    endpoint, url = s3_bucket
    # What a worker host is given: the records and the bucket through its environment (the records'
    # URL holds Redis's password: never on a command line).
    monkeypatch.setenv("EVA_RECORDS_URL", redis_url)
    monkeypatch.setenv("EVA_STORAGE_URL", url)
    monkeypatch.setenv("EVA_S3_ENDPOINT_URL", endpoint)
    hosts = {name: tmp_path / name for name in ("api1", "api2", "worker1", "worker2")}
    logs = [tmp_path / "worker1.log", tmp_path / "worker2.log"]
    with (
        api_host(hosts["api1"], redis_url, s3_bucket) as one,
        api_host(hosts["api2"], redis_url, s3_bucket) as two,
    ):
        health = one.get("/healthz").json()
        assert (health["queue"], health["records"], health["storage"]) == ("redis", "redis", "s3")
        workers = [
            start_worker(hosts[f"worker{i}"], log, queue_url=redis_url)
            for i, log in ((1, logs[0]), (2, logs[1]))
        ]
        try:
            with open(signer_video, "rb") as f:
                res = one.post("/avatars", files={"video": ("clip.mp4", f, "video/mp4")}, data=FAST_OPTIONS)
            assert res.status_code == 202, res.text
            real = res.json()
            assert files_under(hosts["api1"] / "jobs" / "work") == set()  # the upload is in the bucket
            nobody = nobody_video(tmp_path / "nobody.mp4")
            with open(nobody, "rb") as f:
                res = two.post(
                    "/avatars", files={"video": ("nobody.mp4", f, "video/mp4")}, data={"preset": "tiny"}
                )
            assert res.status_code == 202, res.text
            nobody = res.json()
        except BaseException:
            for w in workers:
                stop(w)
            raise
        # The other API host sees every record; each job ran once, on one of the two worker hosts.
        finish_real_and_nobody(two, workers, logs, real["job_id"], nobody["job_id"])
        # The avatar was published by a worker host, into the bucket; no work folder is left anywhere.
        avatar = real["avatar_id"]
        bucket = boto3.client("s3", endpoint_url=endpoint)
        keys = [o["Key"] for o in bucket.list_objects_v2(Bucket="eva-test").get("Contents", [])]
        assert f"service/avatars/{avatar}/.published" in keys and not any("/work/" in k for k in keys), keys
        assert not (hosts["api1"] / "avatars" / avatar).exists()
        for name in ("worker1", "worker2"):
            assert files_under(hosts[name] / "jobs" / "work") == set()

        # Either API host renders it (downloading it once), and a delete on one reaches the other.
        for client in (one, two):
            res = client.post(f"/avatars/{avatar}/render", json={"width": 64, "height": 64})
            assert res.status_code == 200 and res.content[:8] == b"\x89PNG\r\n\x1a\n", res.text
        assert (hosts["api1"] / "avatars" / avatar / "avatar.json").is_file()
        assert two.delete(f"/avatars/{avatar}").status_code in (200, 204)
        assert one.post(f"/avatars/{avatar}/render", json={"width": 64, "height": 64}).status_code == 404
        keys = [o["Key"] for o in bucket.list_objects_v2(Bucket="eva-test").get("Contents", [])]
        assert not any(avatar in k for k in keys), keys
