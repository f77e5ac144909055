"""Owners (``service.accounts``): with a keys file, each owner sees, downloads, deletes and cancels
only their own avatars, animations and jobs (another's answer 404, as an unknown id does), the
job quota is per owner, an admin sees everything, and the keys file is checked at start-up."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.scenes import teacher_avatar
from helpers.service import FAST_OPTIONS
from typer.testing import CliRunner

from eva_engine.avatar import TrainingRecord, save_avatar
from jobs import JobQueue, JobsConfig
from service.accounts import Account, read_accounts
from service.app import create_app
from service.settings import ServiceSettings

signer_video = svc.signer_video  # a fixture
ALICE, BOB, OPS = "alice-key-0123456789", "bob-key-0123456789ab", "ops-key-0123456789abc"
ACCOUNTS = (
    Account(owner="alice", key=ALICE),
    Account(owner="bob", key=BOB),
    Account(owner="ops", key=OPS, admin=True),
)


def make_client(tmp_path, **overrides) -> tuple[TestClient, JobQueue]:
    jobs = JobsConfig(data_dir=tmp_path / "data")
    settings = ServiceSettings(jobs=jobs, preload_body_models=(), accounts=ACCOUNTS, **overrides)
    queue = JobQueue(jobs)
    return TestClient(create_app(settings, queue=queue), base_url="http://127.0.0.1"), queue


def as_(key: str) -> dict[str, str]:
    return {"X-API-Key": key}


def finished_avatar(queue: JobQueue, body, account: str | None) -> str:
    job = queue.store.create({"preset": "tiny"}, filename="mine.mp4", account=account)
    partial = queue.config.data_dir / f"{job.id}.partial"
    save_avatar(teacher_avatar(body, n=500), partial, TrainingRecord(preset="tiny"))
    queue.storage.publish(partial, job.output_id)
    queue.store.update(job.id, state="succeeded", progress=1.0, completed_stage="export")
    return job.output_id


def test_an_owner_never_reaches_anothers_avatars(tmp_path, anny_model):
    client, queue = make_client(tmp_path)
    with client:
        client.app.state.context.avatars._bodies["anny"] = anny_model
        alices = finished_avatar(queue, anny_model, "alice")
        older = finished_avatar(queue, anny_model, None)  # made before accounts existed

        def listed(key: str) -> list[str]:
            return [a["avatar_id"] for a in client.get("/avatars", headers=as_(key)).json()["avatars"]]

        assert listed(ALICE) == [alices] and listed(BOB) == [] and listed(OPS) == [alices, older]
        for method, path in (
            ("GET", f"/avatars/{alices}"),
            ("GET", f"/avatars/{alices}/export"),
            ("POST", f"/avatars/{alices}/render"),
            ("GET", f"/avatars/{alices}/animations"),
            ("GET", f"/avatars/{alices}/controls"),
            ("DELETE", f"/avatars/{alices}"),
            ("GET", f"/avatars/{older}"),
        ):
            res = client.request(method, path, headers=as_(BOB))
            assert res.status_code == 404 and "no avatar with id" in res.json()["detail"], (method, path)
        assert client.get(f"/avatars/{alices}/export", headers=as_(ALICE)).status_code == 200
        assert client.get(f"/avatars/{older}", headers=as_(ALICE)).status_code == 404
        assert client.get(f"/avatars/{older}", headers=as_(OPS)).status_code == 200
        # An animation of hers is hers alone too.
        poses = {"poses": ("m.json", json.dumps([{}]).encode(), "application/json")}
        made = client.post(f"/avatars/{alices}/animations", files=poses, headers=as_(ALICE))
        assert made.status_code == 202, made.text
        animation, job = made.json()["animation_id"], made.json()["job_id"]
        assert client.get(f"/animations/{animation}", headers=as_(BOB)).status_code == 404
        assert client.get(f"/jobs/{job}", headers=as_(BOB)).status_code == 404
        assert client.delete(f"/jobs/{job}", headers=as_(BOB)).status_code == 404
        assert client.get(f"/jobs/{job}", headers=as_(ALICE)).json()["state"] == "queued"
        assert client.delete(f"/avatars/{alices}", headers=as_(BOB)).status_code == 404
        assert client.delete(f"/jobs/{job}", headers=as_(ALICE)).status_code == 200
        assert client.delete(f"/avatars/{alices}", headers=as_(ALICE)).status_code == 204
        assert client.get("/avatars", headers={"X-API-Key": "nobody-0123456789abc"}).status_code == 401
        assert client.get("/avatars").status_code == 401


def test_the_job_quota_is_each_owners(tmp_path, signer_video):
    client, queue = make_client(tmp_path, max_queued_jobs=1)
    video = {"video": ("clip.mp4", signer_video.read_bytes(), "video/mp4")}
    with client:
        first = client.post("/avatars", files=video, data=FAST_OPTIONS, headers=as_(ALICE))
        assert first.status_code == 202, first.text
        res = client.post("/avatars", files=video, data=FAST_OPTIONS, headers=as_(ALICE))
        assert res.status_code == 503 and "of yours" in res.json()["detail"]
        assert client.post("/avatars", files=video, data=FAST_OPTIONS, headers=as_(BOB)).status_code == 202
    assert sorted(job.account for job in queue.store.list()) == ["alice", "bob"]


def test_the_keys_file_is_checked(tmp_path):
    path = tmp_path / "keys.json"

    def keys(*accounts):
        path.write_text(json.dumps({"accounts": list(accounts)}))
        return path

    assert [a.owner for a in read_accounts(keys({"owner": "a", "key": ALICE}))] == ["a"]
    for accounts, reason in (
        ([{"owner": "a", "key": "short-key"}], "at least 16"),
        ([{"owner": "a", "key": ALICE}, {"owner": "a", "key": BOB}], "each owner"),
        ([{"owner": "a", "key": ALICE}, {"owner": "b", "key": ALICE}], "one owner only"),
        ([{"owner": "a b", "key": ALICE}], "pattern"),
    ):
        with pytest.raises(ValueError, match=reason) as refused:
            read_accounts(keys(*accounts))
        assert ALICE not in str(refused.value) and "short-key" not in str(refused.value)  # never a key
    with pytest.raises(ValueError, match="not both"):
        ServiceSettings(jobs=JobsConfig(data_dir=tmp_path), api_key=OPS, accounts=ACCOUNTS)
    settings = ServiceSettings(jobs=JobsConfig(data_dir=tmp_path), host="0.0.0.0", accounts=ACCOUNTS)
    assert settings.trusted_hosts == ["*"]  # keyed: may listen on the network
    from service.cli import app

    result = CliRunner().invoke(app, ["serve", "--api-keys-file", str(keys({"owner": "a", "key": "short"}))])
    assert result.exit_code == 2 and "at least 16" in result.output
