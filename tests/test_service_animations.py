"""The animation endpoints and the page, in-process (FastAPI's TestClient; jobs run in their own
process by the worker's ``JobRunner``, or here by ``JobRun`` as that process would): an avatar
performs a JSON motion and a video; every bad input (no upload, a video without a person, an
avatar that does not exist or is not ready, bad poses and options, over the size and pixel
limits), the API key and the request guard, the queue's quota, the render slots, an attempt
that lost its job, and the pose controls the page uses.

The avatar is the part-coloured teacher avatar published into the service's storage with a
finished job record, as the worker leaves it (the real pipeline runs in the e2e and browser tests).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.scenes import teacher_avatar
from helpers.service import run_job_here

from eva_engine.avatar import TrainingRecord, save_avatar
from eva_engine.data import read_video
from eva_engine.synth.hard import nobody_video
from jobs import JobQueue, JobRun, JobsConfig
from jobs.animation import ANIMATION, AnimationOptions
from service.app import create_app
from service.settings import ServiceSettings

signer_video = svc.signer_video  # a fixture
RAISED = {"joints": {"upperarm01.L": [0.0, 0.0, 1.2]}, "expression": {"jawOpen": 0.6}}


def make_client(tmp_path, **overrides) -> tuple[TestClient, JobQueue]:
    jobs = JobsConfig(data_dir=tmp_path / "data")
    settings = ServiceSettings(jobs=jobs, preload_body_models=(), **overrides)
    queue = JobQueue(jobs)
    return TestClient(create_app(settings, queue=queue), base_url="http://127.0.0.1"), queue


def ready_avatar(queue: JobQueue, body) -> str:
    """A finished avatar job, as a worker publishes it."""
    job = queue.store.create({"preset": "tiny"}, filename="teacher.mp4")
    partial = queue.config.data_dir / "teacher.partial"
    save_avatar(teacher_avatar(body, n=2000), partial, TrainingRecord(preset="tiny"))
    queue.storage.publish(partial, job.output_id)
    queue.store.update(job.id, state="succeeded", progress=1.0, completed_stage="export")
    return job.output_id


@pytest.fixture
def service(tmp_path, anny_model):
    client, queue = make_client(tmp_path, max_upload_mb=1.0)
    queue.test_body_model = anny_model  # jobs run here (run_job) use the session's model
    with client:
        client.app.state.context.avatars._bodies["anny"] = anny_model  # loaded once per test session
        yield client, queue, ready_avatar(queue, anny_model)


def poses_file(doc) -> tuple[str, bytes, str]:
    return ("motion.json", json.dumps(doc).encode(), "application/json")


def run_job(queue: JobQueue, job_id: str) -> str:
    """Run the job in this process, as its own process would (the session's body model)."""
    return run_job_here(queue, job_id, queue.test_body_model)


def test_animate_json_poses_end_to_end(service):
    client, queue, avatar_id = service
    motion = {"fps": 8, "poses": [{}, {}, RAISED, RAISED]}
    res = client.post(
        f"/avatars/{avatar_id}/animations",
        files={"poses": poses_file(motion)},
        data={"width": "64", "height": "80", "smooth_s": "0"},
    )
    assert res.status_code == 202, res.text
    created = res.json()
    info = client.get(created["animation_url"]).json()
    assert info["state"] == "queued" and info["avatar_id"] == avatar_id and info["video_url"] is None
    job = client.get(created["job_url"]).json()
    assert job["kind"] == "animation" and job["avatar_id"] == avatar_id
    assert job["animation_id"] == created["animation_id"] and job["options"]["width"] == 64
    assert client.get(f"/animations/{created['animation_id']}/video").status_code == 409
    # As a worker runs it: the job in its own process (``python -m jobs run``), under its limits.
    assert queue.run_pending() == 1
    assert client.get(created["job_url"]).json()["state"] == "succeeded", client.get(created["job_url"]).text
    info = client.get(created["animation_url"]).json()
    assert info["state"] == "succeeded" and info["progress"] == 1.0 and info["stage"] == "export"
    assert (info["frames"], info["width"], info["height"], info["fps"]) == (4, 64, 80, 8.0)
    video = client.get(info["video_url"])
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    path = queue.config.data_dir / "check.mp4"
    path.write_bytes(video.content)
    clip = read_video(path)
    f = clip.frames.astype(int)
    assert f.shape == (4, 80, 64, 3)
    assert np.abs(f[1] - f[0]).mean() < 0.5 < np.abs(f[2] - f[1]).mean()  # still, then the arm moves
    # Listed under the avatar; not an avatar itself.
    listed = client.get(f"/avatars/{avatar_id}/animations").json()["animations"]
    assert [a["animation_id"] for a in listed] == [created["animation_id"]]
    assert [a["avatar_id"] for a in client.get("/avatars").json()["avatars"]] == [avatar_id]
    assert not (queue.config.work_dir / created["job_id"]).exists()
    # Deleted: gone, files and all.
    assert client.delete(created["animation_url"]).status_code == 204
    assert client.get(created["animation_url"]).status_code == 404
    assert not queue.storage.animation_exists(created["animation_id"])


@pytest.mark.slow
def test_animate_a_video(service, signer_video):
    client, queue, avatar_id = service
    res = client.post(
        f"/avatars/{avatar_id}/animations",
        files={"video": ("signer.mp4", signer_video.read_bytes(), "video/mp4")},
        data={"camera": "driving", "side_by_side": "true", "fit_scale": "0.1"},
    )
    assert res.status_code == 202, res.text
    created = res.json()
    assert run_job(queue, created["job_id"]) == "succeeded", client.get(created["job_url"]).json()
    info = client.get(created["animation_url"]).json()
    assert info["frames"] == svc.SIGNER_FRAMES and (info["width"], info["height"]) == (512, 256)
    assert info["driving_frames_without_person"] == 0 and info["source"] == "signer.mp4"


def test_form_fields_are_the_animation_request(service):
    """The form is AnimationRequest: the camera defaults to the front preset (a name or JSON text
    otherwise), empty fields take their default, unknown fields are ignored."""
    client, queue, avatar_id = service
    form = {"fps": "", "max_size": "256", "hat": "red", "background": ["0", "0.5", "1"]}
    res = client.post(f"/avatars/{avatar_id}/animations", files={"poses": poses_file([{}])}, data=form)
    assert res.status_code == 202, res.text
    options = client.get(res.json()["job_url"]).json()["options"]
    expected = AnimationOptions(avatar_id=avatar_id, camera="front", max_size=256, background=(0, 0.5, 1))
    assert options == expected.model_dump(mode="json")
    res = client.post(
        f"/avatars/{avatar_id}/animations",
        files={"poses": poses_file([{}])},
        data={"camera": ' {"yaw": 30} '},
    )
    assert client.get(res.json()["job_url"]).json()["options"]["camera"]["yaw"] == 30.0


def test_no_driving_upload_is_422(service):
    client, _, avatar_id = service
    res = client.post(f"/avatars/{avatar_id}/animations", data={"camera": "front"})
    assert res.status_code == 422 and "no driving motion" in res.json()["detail"]
    both = {"video": ("a.mp4", b"x" * 100, "video/mp4"), "poses": poses_file([{}])}
    res = client.post(f"/avatars/{avatar_id}/animations", files=both)
    assert res.status_code == 422 and "not both" in res.json()["detail"]


def test_a_video_without_a_person_fails_its_job_with_the_reason(service, tmp_path):
    client, queue, avatar_id = service
    video = nobody_video(tmp_path / "nobody.mp4")
    res = client.post(
        f"/avatars/{avatar_id}/animations", files={"video": ("nobody.mp4", video.read_bytes(), "video/mp4")}
    )
    assert res.status_code == 202, res.text  # a valid video: whether someone is in it, the job finds out
    created = res.json()
    assert run_job(queue, created["job_id"]) == "failed"
    info = client.get(created["animation_url"]).json()
    assert info["state"] == "failed" and "no person" in info["error"] and info["video_url"] is None
    assert str(tmp_path) not in info["error"]
    res = client.get(f"/animations/{created['animation_id']}/video")
    assert res.status_code == 409 and "no person" in res.json()["detail"]


def test_an_avatar_that_does_not_exist_is_404(service):
    client, _, _ = service
    for avatar in ("0123456789abcdef0123456789abcdef", "not-an-id", "..%2F..%2Fetc"):
        res = client.post(f"/avatars/{avatar}/animations", files={"poses": poses_file([{}])})
        assert res.status_code == 404, res.text
        assert client.get(f"/avatars/{avatar}/animations").status_code == 404
        assert client.get(f"/avatars/{avatar}/controls").status_code == 404
    for path in (
        "/animations/0123456789abcdef0123456789abcdef",
        "/animations/nope",
        "/animations/0123456789abcdef0123456789abcdef/video",
    ):
        assert client.get(path).status_code == 404


def test_an_avatar_still_being_made_is_409(service):
    client, queue, _ = service
    pending = queue.store.create({"preset": "tiny"}, filename="later.mp4")
    res = client.post(f"/avatars/{pending.output_id}/animations", files={"poses": poses_file([{}])})
    assert res.status_code == 409 and "not ready" in res.json()["detail"]


@pytest.mark.parametrize(
    ("files", "data", "needle"),
    [
        ({"poses": poses_file({"poses": [{"joints": {"wing.L": [0, 0, 1]}}]})}, {}, "wing.L"),
        ({"poses": poses_file({"poses": []})}, {}, "at least 1"),
        ({"poses": ("m.json", b"{not json", "application/json")}, {}, "not valid JSON"),
        ({"poses": ("m.json", b"", "application/json")}, {}, "empty"),
        ({"poses": poses_file([{}])}, {"camera": "driving"}, "need a driving video"),
        ({"poses": poses_file([{}])}, {"side_by_side": "true"}, "need a driving video"),
        ({"poses": poses_file([{}])}, {"camera": "sideways"}, "sideways"),
        ({"poses": poses_file([{}])}, {"camera": '{"pitch": 95}'}, "pitch"),
        ({"poses": poses_file([{}])}, {"camera": "{bad"}, "valid JSON"),
        ({"poses": poses_file([{}])}, {"fps": "0"}, "fps"),
        ({"poses": poses_file([{}])}, {"width": "100000"}, "width"),
        ({"poses": ("m.json", b"[" * 100_000 + b"]" * 100_000, "application/json")}, {}, "nested too deeply"),
        # Counted before each pose is validated: the budget speaks, not the first unknown joint.
        ({"poses": poses_file([{"joints": {"wing.L": [0, 0, 1]}}] * 5000)}, {}, "5000 frames of 512x512"),
        ({"video": ("clip.mp4", b"just some text, no video" * 10, "video/mp4")}, {}, "not a readable video"),
        ({"video": ("clip.mp4", b"", "video/mp4")}, {}, "empty"),
    ],
    ids=[
        "unknown-joint",
        "no-poses",
        "bad-json",
        "empty-poses",
        "driving-camera",
        "side-by-side",
        "camera-name",
        "camera-bounds",
        "camera-json",
        "fps",
        "width",
        "nested-json",
        "over-the-budget",
        "not-a-video",
        "empty-video",
    ],
)
def test_bad_uploads_and_options_are_422_and_leave_nothing(service, files, data, needle):
    client, queue, avatar_id = service
    res = client.post(f"/avatars/{avatar_id}/animations", files=files, data=data)
    assert res.status_code == 422 and needle in res.text, res.text
    assert list(queue.config.work_dir.iterdir()) == []
    assert client.get(f"/avatars/{avatar_id}/animations").json() == {"animations": []}


def test_uploads_over_the_size_limit_are_413(service):
    client, queue, avatar_id = service
    big = {"video": ("big.mp4", b"\x00" * (2 * 1024 * 1024), "video/mp4")}
    res = client.post(f"/avatars/{avatar_id}/animations", files=big)
    assert res.status_code == 413 and "limit" in res.json()["detail"]
    assert list(queue.config.work_dir.iterdir()) == []


def test_pose_controls_and_the_page(service):
    client, _, avatar_id = service
    doc = client.get(f"/avatars/{avatar_id}/controls", params={"aspect": 0.75}).json()
    assert doc["body_model"] == "anny"
    names = {c["name"] for c in doc["controls"]}
    assert {
        "arm_out.L",
        "elbow.R",
        "fingers.L",
        "fingers.R",
        "jaw_open",
        "smile",
        "brows_up",
        "blink",
    } <= names
    target, distance = doc["framing"]["target"], doc["framing"]["distance"]
    assert -0.5 < target[1] < 0.8 and 1.0 < distance < 8.0
    # A pose the page would send, from a control: it renders.
    arm = next(c for c in doc["controls"] if c["name"] == "arm_out.L")
    term = arm["joints"][0]
    pose = {"joints": {term["joint"]: [a * 1.2 for a in term["axis"]]}}
    camera = {"yaw": 20, "pitch": 5, **doc["framing"]}
    res = client.post(
        f"/avatars/{avatar_id}/render", json={"pose": pose, "camera": camera, "width": 48, "height": 64}
    )
    assert res.status_code == 200 and res.headers["content-type"] == "image/png"
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    for asset in ("/static/app.js", "/static/style.css"):
        assert client.get(asset).status_code == 200
    assert "http" not in page.text.replace("http-equiv", "")  # nothing from a CDN: the service is offline


def test_api_key_guards_animations_but_not_the_page(tmp_path, anny_model):
    client, queue = make_client(tmp_path, api_key="s3cret-key-0123456789")
    with client:
        avatar_id = ready_avatar(queue, anny_model)
        assert client.get("/").status_code == 200 and client.get("/static/app.js").status_code == 200
        url = f"/avatars/{avatar_id}/animations"
        assert client.post(url, files={"poses": poses_file([{}])}).status_code == 401
        assert client.get(url).status_code == 401
        assert client.get(f"/avatars/{avatar_id}/controls").status_code == 401
        assert client.get("/animations/0123456789abcdef0123456789abcdef").status_code == 401
        ok = client.post(
            url, files={"poses": poses_file([{}])}, headers={"X-API-Key": "s3cret-key-0123456789"}
        )
        assert ok.status_code == 202, ok.text


def test_cancel_a_queued_animation(service):
    client, queue, avatar_id = service
    res = client.post(f"/avatars/{avatar_id}/animations", files={"poses": poses_file([{}, RAISED])})
    created = res.json()
    res = client.delete(created["job_url"])
    assert res.status_code == 200 and res.json()["state"] == "cancelled"
    assert client.get(created["animation_url"]).json()["state"] == "cancelled"
    assert not (queue.config.work_dir / created["job_id"]).exists()


def test_an_attempt_that_lost_its_animation_job_writes_nothing(service):
    """Recovery gave the job to another worker while this attempt ran: none of its writes land,
    nothing is published, and the new owner's run publishes the animation once."""
    client, queue, avatar_id = service
    res = client.post(
        f"/avatars/{avatar_id}/animations",
        files={"poses": poses_file([{}, RAISED])},
        data={"width": "32", "height": "32"},
    )
    created = res.json()
    store = queue.store
    lost = store.claim(created["job_id"], "elsewhere:1:10:100:a")
    store.update(lost.id, worker="elsewhere:1:11:101:b")  # taken over (as recovery + a claim would)
    run = JobRun(queue.config, store, queue.storage, lost, lost.worker, ANIMATION)
    run.add_body_model(queue.test_body_model)
    assert run.execute() is None  # it stopped at its first write
    job = store.get(lost.id)
    assert job.state == "running" and job.worker.endswith(":b") and job.completed_stage is None
    assert not queue.storage.animation_exists(created["animation_id"])
    assert not store.update(lost.id, owner=lost.worker, progress=0.5)
    store.update(lost.id, state="queued", worker=None)
    assert run_job(queue, lost.id) == "succeeded"
    assert queue.storage.animation_exists(created["animation_id"])


def test_animation_uploads_meet_the_guard_and_the_quota(tmp_path, anny_model):
    """The upload rule covers the animation endpoint (its own body limit, not the 64 KB JSON one),
    poses have their own smaller cap, the rendered frames must fit the job's pixel budget, and
    the queue's quota counts animation jobs too."""
    jobs = JobsConfig(data_dir=tmp_path / "data", max_frame_pixels=64 * 64 * 50)
    settings = ServiceSettings(
        jobs=jobs, preload_body_models=(), max_poses_mb=0.01, max_queued_jobs=2, max_render_pixels=128 * 128
    )
    queue = JobQueue(jobs)
    with TestClient(create_app(settings, queue=queue), base_url="http://127.0.0.1") as client:
        client.app.state.context.avatars._bodies["anny"] = anny_model
        avatar_id = ready_avatar(queue, anny_model)
        url = f"/avatars/{avatar_id}/animations"
        small = {"width": "64", "height": "64"}
        # Over 64 KB (the JSON limit) but within the upload's: reaches the endpoint, whose poses cap says no.
        big = poses_file({"poses": [{}] * 40_000})
        res = client.post(url, files={"poses": big}, data=small)
        assert res.status_code == 413 and "limit" in res.json()["detail"], res.text
        # 60 frames of 64x64 are over a budget of 50.
        res = client.post(url, files={"poses": poses_file([{}] * 60)}, data=small)
        assert res.status_code == 422 and "M pixels" in res.json()["detail"], res.text
        # One frame over the render limit.
        res = client.post(url, files={"poses": poses_file([{}])}, data={"width": "256", "height": "256"})
        assert res.status_code == 422 and "over the limit" in res.json()["detail"], res.text
        # Out-of-range values in a pose: the render's bounds and the body model's ranges.
        for pose, needle in (
            ({"transl": [1e300, 0, 0]}, "transl"),
            ({"expression": {"jawOpen": 2.0}}, "range"),
        ):
            res = client.post(url, files={"poses": poses_file([pose])}, data=small)
            assert res.status_code == 422 and needle in res.text, res.text
        assert list(queue.config.work_dir.iterdir()) == []
        for _ in range(2):
            assert client.post(url, files={"poses": poses_file([{}])}, data=small).status_code == 202
        res = client.post(url, files={"poses": poses_file([{}])}, data=small)
        assert res.status_code == 503 and "quota" in res.json()["detail"] and res.headers["retry-after"]
        # Cross-site writes are refused here too.
        res = client.post(url, files={"poses": poses_file([{}])}, headers={"Origin": "https://evil.example"})
        assert res.status_code == 403


def test_pose_controls_share_the_render_slots(service):
    """Loading an avatar and posing its body cost like a render: with every render slot taken
    and no room to wait, the controls are refused with Retry-After, like a render."""
    client, _, avatar_id = service
    gate = client.app.state.context.renders
    gate.running, waiting = gate.slots, gate.waiting
    gate.waiting = 0
    try:
        res = client.get(f"/avatars/{avatar_id}/controls")
        assert res.status_code == 503 and res.headers["retry-after"] == "1", res.text
    finally:
        gate.running, gate.waiting = 0, waiting
    assert client.get(f"/avatars/{avatar_id}/controls").status_code == 200
