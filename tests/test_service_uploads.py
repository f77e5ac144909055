"""Hostile uploads, in-process: a 16k x 16k frame refused from its headers (and what the probe
cost), containers other than mp4/mov/mkv/webm/avi refused before FFmpeg parses them, a duration
found from the packets when the headers have none, the frames x pixels budget, the caps on job
options, the queued-job quota, and failures that answer with a reason and leave nothing behind
(a body cut off after its video part, a full disk, a queue that is down)."""

from __future__ import annotations

import errno
import json
import sqlite3
import subprocess
import sys

import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.service import FAST_OPTIONS, free_port, gradient_video

from eva_engine.synth.hard import nobody_video
from jobs import JobsConfig
from service.app import create_app
from service.routers import avatars as avatars_router
from service.settings import ServiceSettings

signer_video = svc.signer_video  # fixtures
huge_frame_video = svc.huge_frame_video


def make_client(tmp_path, jobs: dict | None = None, **overrides) -> TestClient:
    config = JobsConfig(data_dir=tmp_path / "data", **(jobs or {}))
    settings = ServiceSettings(jobs=config, preload_body_models=(), **overrides)
    return TestClient(create_app(settings), base_url="http://127.0.0.1")


def upload(client, content: bytes, name="clip.mp4", **options):
    return client.post("/avatars", files={"video": (name, content, "video/mp4")}, data=options)


def leftovers(tmp_path) -> list:
    data = tmp_path / "data"
    return [p for folder in (data / "jobs" / "work", data / "avatars") for p in folder.rglob("*")]


def test_a_16k_frame_is_refused_from_its_headers(tmp_path, huge_frame_video):
    command = [sys.executable, "-m", "jobs", "probe", str(huge_frame_video)]
    probe = subprocess.run(command, capture_output=True, check=True)
    answer = json.loads(probe.stdout.decode().splitlines()[-1])
    assert "16000x16000" in answer["error"] and "4096" in answer["error"]
    assert answer["peak_rss_mb"] < 400, answer  # the old in-process probe peaked at 2.5 GB on it
    with make_client(tmp_path) as client:
        res = upload(client, huge_frame_video.read_bytes())
        assert res.status_code == 422 and "16000x16000" in res.json()["detail"], res.text
    assert leftovers(tmp_path) == []


PLAYLIST = b"#EXTM3U\n#EXT-X-TARGETDURATION:10\n#EXTINF:10,\nfile:///etc/hostname\n#EXT-X-ENDLIST\n"
CONCAT = b"ffconcat version 1.0\nfile '/etc/hostname'\n"


def png_image() -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (64, 48), (200, 100, 50)).save(buf, format="PNG")
    return buf.getvalue()


@pytest.mark.parametrize(
    ("content", "name"),
    [(PLAYLIST, "list.m3u8"), (CONCAT, "list.ffconcat"), (None, "still.png")],
    ids=["hls", "concat", "png"],
)
def test_other_demuxers_are_refused(tmp_path, content, name):
    with make_client(tmp_path) as client:
        res = upload(client, content if content is not None else png_image(), name=name)
    assert res.status_code == 422 and "accepted containers" in res.json()["detail"], res.text
    assert leftovers(tmp_path) == []


def test_a_duration_missing_from_the_headers_is_measured(tmp_path):
    video = gradient_video(tmp_path / "live.mkv", frames=30, side=64, live=True)  # 2.9 s, no duration field
    with make_client(tmp_path, max_video_seconds=1.0) as client:
        res = upload(client, video.read_bytes(), name="live.mkv")
    assert res.status_code == 422 and "2.9 s long" in res.json()["detail"], res.text


def test_frames_over_the_pixel_budget_are_refused_at_upload(tmp_path):
    video = gradient_video(tmp_path / "big.mp4", frames=40, side=2048)  # 40 x 4.2 M pixels = 168 M
    with make_client(tmp_path) as client:
        res = upload(client, video.read_bytes(), max_frames="2000", max_size="2048")
        assert res.status_code == 422 and "lower max_frames or max_size" in res.json()["detail"], res.text
        # The same video within the budget: resized to 512 px, 40 frames are 10 M pixels.
        assert upload(client, video.read_bytes(), max_frames="2000", max_size="512").status_code == 202


def test_options_over_their_caps_are_422(tmp_path, signer_video):
    with make_client(tmp_path) as client:
        caps = ({"iterations": "100000"}, {"max_frames": "5000"}, {"max_size": "4096"})
        for options in caps:
            needle = next(iter(options))
            res = upload(client, signer_video.read_bytes(), **options)
            assert res.status_code == 422 and needle in res.text, res.text
    assert leftovers(tmp_path) == []


def test_queued_jobs_have_a_quota(tmp_path, signer_video):
    with make_client(tmp_path, max_queued_jobs=1) as client:
        assert upload(client, signer_video.read_bytes(), **FAST_OPTIONS).status_code == 202
        res = upload(client, signer_video.read_bytes(), **FAST_OPTIONS)
        assert res.status_code == 503 and int(res.headers["retry-after"]) > 0
        assert "quota" in res.json()["detail"]
        assert len(client.get("/avatars").json()["avatars"]) == 1
    assert len([p for p in (tmp_path / "data" / "jobs" / "work").iterdir()]) == 1


def test_a_body_cut_off_after_its_video_part_leaves_no_job(tmp_path, signer_video):
    video = signer_video.read_bytes()

    def body():  # chunked (no Content-Length): the video part is complete, then a huge field
        yield (
            b'--x\r\nContent-Disposition: form-data; name="video"; filename="a.mp4"\r\n'
            b"Content-Type: video/mp4\r\n\r\n" + video + b"\r\n"
        )
        yield b'--x\r\nContent-Disposition: form-data; name="preset"\r\n\r\n'
        for _ in range(40):
            yield b"a" * 65536

    with make_client(tmp_path, max_upload_mb=1.0) as client:
        headers = {"content-type": "multipart/form-data; boundary=x"}
        res = client.post("/avatars", content=body(), headers=headers)
        assert res.status_code == 413, res.text
        assert client.get("/avatars").json() == {"avatars": []}
    assert leftovers(tmp_path) == []


def test_a_full_disk_is_507_and_leaves_nothing(tmp_path, signer_video, monkeypatch):
    def no_space(source, dest, max_bytes):
        dest.write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(avatars_router, "save_upload", no_space)
    with make_client(tmp_path) as client:
        res = upload(client, signer_video.read_bytes())
    assert res.status_code == 507 and "disk is full" in res.json()["detail"], res.text
    assert leftovers(tmp_path) == []


def test_job_records_on_a_full_disk_are_507_not_busy(tmp_path, signer_video, monkeypatch):
    def full(*args, **kwargs):
        err = sqlite3.OperationalError("database or disk is full")
        err.sqlite_errorcode = 13  # SQLITE_FULL, as sqlite3 sets it
        raise err

    with make_client(tmp_path) as client:
        monkeypatch.setattr(client.app.state.context.queue.store, "create", full)
        res = upload(client, signer_video.read_bytes())
    assert res.status_code == 507 and "disk is full" in res.json()["detail"], res.text
    assert "retry-after" not in res.headers
    assert leftovers(tmp_path) == []


def test_a_queue_that_is_down_is_503_without_internals(tmp_path, signer_video):
    url = f"redis://127.0.0.1:{free_port()}/0"  # nothing listens there
    with make_client(tmp_path, jobs={"queue_url": url}) as client:
        res = upload(client, signer_video.read_bytes(), **FAST_OPTIONS)
        assert res.status_code == 503 and res.headers["retry-after"] == "1", res.text
        assert "unavailable" in res.text and "redis" not in res.text.lower() and "127.0.0.1" not in res.text
        assert client.get("/avatars").json() == {"avatars": []}
    assert leftovers(tmp_path) == []


def test_a_clip_too_short_to_train_on_is_refused_at_upload(tmp_path):
    """A job needs ``MIN_FRAMES`` frames (half are held out to score the avatar): fewer is a 422
    with the reason, before anything is queued."""
    from jobs.options import MIN_FRAMES

    short = nobody_video(tmp_path / "short.mp4", frames=MIN_FRAMES - 3)
    with make_client(tmp_path) as client:
        res = upload(client, short.read_bytes(), preset="tiny")
        assert res.status_code == 422, res.text
        assert f"has {MIN_FRAMES - 3} frames; an avatar needs at least {MIN_FRAMES}" in res.json()["detail"]
        assert client.get("/avatars").json() == {"avatars": []}
    assert leftovers(tmp_path) == []
