"""The API in-process (FastAPI's TestClient, no worker): uploads and their limits, ids, the
lifecycle of a job nobody runs yet (409 until ready, cancel), the API key and the docs."""

from __future__ import annotations

import re
import time

import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.service import FAST_OPTIONS
from pydantic import ValidationError

from eva_engine.recipes import METHODS, PRESETS
from eva_engine.specs.camera import CAMERA_PRESETS
from eva_engine.synth.hard import nobody_video
from jobs import JobsConfig
from jobs.options import MAX_FRAMES, JobOptions
from service.animation_schemas import AnimationForm
from service.app import create_app
from service.schemas import AvatarForm
from service.settings import ServiceSettings

signer_video = svc.signer_video  # a fixture


def make_client(tmp_path, **overrides) -> TestClient:
    jobs = JobsConfig(data_dir=tmp_path / "data")
    settings = ServiceSettings(jobs=jobs, preload_body_models=(), **overrides)
    return TestClient(create_app(settings), base_url="http://127.0.0.1")


@pytest.fixture
def client(tmp_path):
    with make_client(tmp_path, max_upload_mb=1.0) as c:
        yield c


def leftovers(tmp_path) -> list:
    """Files under the work and avatar folders (should be none after a rejected upload)."""
    data = tmp_path / "data"
    return [p for folder in (data / "jobs" / "work", data / "avatars") for p in folder.rglob("*")]


def upload(client, content: bytes, name="clip.mp4", **options):
    return client.post("/avatars", files={"video": (name, content, "video/mp4")}, data=options)


def test_health_and_docs(client):
    health = client.get("/healthz").json()
    assert health["status"] == "ok" and health["queue"] == "sqlite" and health["jobs"]["queued"] == 0
    assert client.get("/docs").status_code == 200
    spec = client.get("/openapi.json").json()
    paths = spec["paths"]
    for path in (
        "/avatars",
        "/avatars/{avatar_id}",
        "/avatars/{avatar_id}/render",
        "/avatars/{avatar_id}/export",
        "/jobs/{job_id}",
        "/healthz",
    ):
        assert path in paths, path
    render = spec["components"]["schemas"]["RenderRequest"]
    assert render["examples"][0]["pose"]["joints"]


def test_the_page_offers_the_registered_presets_and_methods(client):
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "/static/options.js" in page.text
    res = client.get("/page/options")
    assert res.status_code == 200
    upload_form = res.json()["forms"]["upload-form"]["selects"]
    assert [c["value"] for c in upload_form["preset"]["choices"]] == list(PRESETS)
    assert upload_form["preset"]["default"] == "fast"  # JobOptions' default
    assert [c["value"] for c in upload_form["method"]["choices"]] == list(METHODS)
    assert {"value": "3dgs+body", "label": "3dgs+body (baseline)"} in upload_form["method"]["choices"]
    assert "/page/options" in client.get("/openapi.json").json()["paths"]


def test_the_page_s_tooltips_are_the_api_s_field_descriptions(client):
    """One text per option: the page shows the schema's own description, and the HTML types none."""
    forms = client.get("/page/options").json()["forms"]
    for form_id, schema in (("upload-form", AvatarForm), ("animate-form", AnimationForm)):
        hints = forms[form_id]["hints"]
        described = {n: f.description for n, f in schema.model_fields.items() if f.description}
        assert hints == described and hints, form_id
    assert "antialiased" in forms["upload-form"]["hints"]["face_closeups"]
    assert "title=" not in _form_html(client, "upload-form")


def test_the_page_bounds_its_fields_as_the_api_does(client):
    """Every number field's bounds are where the API starts to refuse (an inclusive bound is
    accepted and a hair past it is not; an exclusive one is refused and a hair inside accepted);
    the animation's cameras are the presets and the driving video's."""
    forms = client.get("/page/options").json()["forms"]

    def accepted(schema, name, value) -> bool:
        try:
            schema.model_validate({name: value})
        except ValidationError:
            return False
        return True

    hair = 1e-6
    for form_id, schema in (("upload-form", AvatarForm), ("animate-form", AnimationForm)):
        numbers = forms[form_id]["numbers"]
        page_fields = re.findall(r'name="(\w+)" type="number"', _form_html(client, form_id))
        assert len(page_fields) >= 3 and set(page_fields) <= set(numbers), (page_fields, numbers)
        for name, field in numbers.items():
            assert field["minimum"] is not None or field["exclusive_minimum"] is not None, name
            if field["minimum"] is not None:
                low = field["minimum"]
                assert accepted(schema, name, low) and not accepted(schema, name, low - hair), name
            else:
                low, top = field["exclusive_minimum"], field["maximum"] or field["exclusive_maximum"]
                inside = low + (1 if top is None else min(1, (top - low) / 2))
                assert not accepted(schema, name, low) and accepted(schema, name, inside), name
            if field["maximum"] is not None:
                high = field["maximum"]
                assert accepted(schema, name, high) and not accepted(schema, name, high + hair), name
            elif field["exclusive_maximum"] is not None:
                assert not accepted(schema, name, field["exclusive_maximum"]), name
            if field["default"] is not None:
                assert accepted(schema, name, field["default"]), name
    cameras = forms["animate-form"]["selects"]["camera"]
    assert [c["value"] for c in cameras["choices"]] == [*CAMERA_PRESETS, "driving"]
    assert cameras["default"] == "front"  # AnimationForm's default


def _form_html(client, form_id: str) -> str:
    return re.search(rf'<form id="{form_id}".*?</form>', client.get("/").text, re.S).group(0)


def test_upload_queues_a_job_that_can_be_cancelled(client, signer_video, tmp_path):
    res = upload(client, signer_video.read_bytes(), name="me.mp4", **FAST_OPTIONS)
    assert res.status_code == 202, res.text
    ids = res.json()
    job = client.get(f"/jobs/{ids['job_id']}").json()
    assert job["state"] == "queued" and job["progress"] == 0.0 and job["avatar_id"] == ids["avatar_id"]
    assert job["options"]["preset"] == "tiny" and job["options"]["max_frames"] == svc.SIGNER_FRAMES
    assert job["filename"] == "me.mp4"
    work = tmp_path / "data" / "jobs" / "work" / ids["job_id"]
    assert [p.name for p in work.iterdir()] == ["input.video"]  # not the name the user gave
    avatar = client.get(f"/avatars/{ids['avatar_id']}").json()
    assert avatar["status"] == "pending" and avatar["num_gaussians"] is None
    # Not finished yet: 409 with the reason.
    for res, reason in (
        (client.post(f"/avatars/{ids['avatar_id']}/render", json={}), "its job is queued"),
        (client.get(f"/avatars/{ids['avatar_id']}/export"), "its job is queued"),
        (client.delete(f"/avatars/{ids['avatar_id']}"), f"cancel job {ids['job_id']} first"),
    ):
        assert res.status_code == 409 and reason in res.json()["detail"], res.text
    # Cancel: at once for a queued job; its upload is removed.
    res = client.delete(f"/jobs/{ids['job_id']}")
    assert res.status_code == 200 and res.json()["state"] == "cancelled"
    assert not work.exists()
    assert client.delete(f"/jobs/{ids['job_id']}").status_code == 409
    res = client.post(f"/avatars/{ids['avatar_id']}/render")
    assert res.status_code == 409 and "cancelled" in res.json()["detail"]
    assert client.get(f"/avatars/{ids['avatar_id']}").json()["status"] == "cancelled"
    # A cancelled avatar can be deleted: then it is gone.
    assert client.delete(f"/avatars/{ids['avatar_id']}").status_code == 204
    assert client.get(f"/avatars/{ids['avatar_id']}").status_code == 404
    assert client.get("/avatars").json() == {"avatars": []}


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (b"", "empty"),
        (b"this is a text file, not a video" * 10, "not a readable video"),
        (b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8, "video"),
    ],
    ids=["empty", "text", "corrupt-mp4"],
)
def test_not_a_video_is_422_and_leaves_nothing(client, tmp_path, content, needle):
    res = upload(client, content)
    assert res.status_code == 422, res.text
    assert needle in res.json()["detail"] and str(tmp_path) not in res.json()["detail"]
    assert leftovers(tmp_path) == [] and client.get("/avatars").json() == {"avatars": []}


def test_truncated_and_frameless_videos_are_422(client, signer_video, tmp_path):
    data = signer_video.read_bytes()
    res = upload(client, data[: len(data) // 3])
    assert res.status_code == 422, res.text
    import av
    import numpy as np

    empty = tmp_path / "sound.mp4"  # a valid mp4 with zero video frames (only sound)
    with av.open(str(empty), "w", format="mp4") as container:
        stream = container.add_stream("aac", rate=16000)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
        frame.sample_rate = 16000
        for packet in [*stream.encode(frame), *stream.encode(None)]:
            container.mux(packet)
    res = upload(client, empty.read_bytes())
    detail = res.json()["detail"]
    assert res.status_code == 422 and "no video stream" in detail and str(tmp_path) not in detail, res.text
    assert leftovers(tmp_path) == []


def test_upload_over_the_size_limit_is_413(client, tmp_path):
    big = b"\x00" * (2 * 1024 * 1024)
    res = upload(client, big)
    assert res.status_code == 413 and "limit" in res.json()["detail"]

    def chunks():  # no Content-Length: stopped while streaming
        for _ in range(40):
            yield b"--x\r\n" + b"\x00" * 65536

    headers = {"content-type": "multipart/form-data; boundary=x"}
    res = client.post("/avatars", content=chunks(), headers=headers)
    assert res.status_code == 413, res.text
    assert leftovers(tmp_path) == []


def test_video_over_the_length_limit_is_422(tmp_path, signer_video):
    with make_client(tmp_path, max_video_seconds=0.1) as client:
        res = upload(client, signer_video.read_bytes())
    assert res.status_code == 422 and "limit" in res.json()["detail"], res.text
    assert leftovers(tmp_path) == []


def test_form_fields_are_the_job_options(client, signer_video):
    """The form is JobOptions: empty fields take their default, unknown fields are ignored, and the
    OpenAPI schema shows the model's bounds."""
    res = upload(client, signer_video.read_bytes(), preset="tiny", iterations="", max_size="256", hat="red")
    assert res.status_code == 202, res.text
    options = client.get(f"/jobs/{res.json()['job_id']}").json()["options"]
    assert options == {**JobOptions(preset="tiny", max_size=256).model_dump(), "preset": "tiny"}
    form = client.get("/openapi.json").json()["components"]["schemas"]["AvatarForm"]["properties"]
    assert form["max_frames"]["maximum"] == MAX_FRAMES and form["preset"]["enum"] == list(PRESETS)


@pytest.mark.parametrize(
    ("options", "needle"),
    [
        ({"preset": "huge"}, "preset"),
        ({"max_frames": "0"}, "max_frames"),
        ({"body_model": "smpl"}, "body_model"),
        ({"image_scale": "2"}, "image_scale"),
        ({"iterations": "many"}, "iterations"),
        ({"method": "gart"}, "method"),
    ],
    ids=["preset", "max_frames", "body_model", "image_scale", "iterations", "method"],
)
def test_bad_options_are_422(client, signer_video, tmp_path, options, needle):
    res = upload(client, signer_video.read_bytes(), **options)
    assert res.status_code == 422 and needle in res.text, res.text
    assert leftovers(tmp_path) == []


def test_missing_video_field_is_422(client):
    res = client.post("/avatars", data={"preset": "tiny"})
    assert res.status_code == 422 and "video" in res.text


@pytest.mark.parametrize(
    "path",
    [
        "/jobs/0123456789abcdef0123456789abcdef",
        "/avatars/0123456789abcdef0123456789abcdef",
        "/avatars/not-an-id",
        "/avatars/..%2F..%2Fetc%2Fpasswd",
        "/avatars/%2e%2e",
        "/jobs/..%2Fjobs.db",
        "/avatars/0123456789ABCDEF0123456789ABCDEF",
    ],
)
def test_unknown_and_malformed_ids_are_404(client, path):
    for method, suffix in (("get", ""), ("delete", ""), ("post", "/render"), ("get", "/export")):
        if path.startswith("/jobs") and suffix:
            continue
        res = getattr(client, method)(path + suffix)
        assert res.status_code == 404, (method, path + suffix, res.text)


def test_api_key(tmp_path):
    with make_client(tmp_path, api_key="s3cret-key-0123456789") as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/avatars").status_code == 401
        assert client.get("/avatars", headers={"X-API-Key": "wrong"}).status_code == 401
        assert client.get("/avatars", headers={"X-API-Key": "s3cret-key-0123456789"}).status_code == 200


def test_job_records_survive_a_restart_of_the_api(tmp_path, signer_video):
    with make_client(tmp_path) as client:
        ids = upload(client, signer_video.read_bytes(), **FAST_OPTIONS).json()
    with make_client(tmp_path) as client:
        job = client.get(f"/jobs/{ids['job_id']}").json()
        assert job["state"] == "queued" and job["options"]["iterations"] == 6
        assert job["options"]["method"] is None
        assert client.get("/avatars").json()["avatars"][0]["avatar_id"] == ids["avatar_id"]


def test_render_body_is_validated_before_the_avatar_is_loaded(client, tmp_path):
    nobody_video(tmp_path / "nobody.mp4")  # valid video: accepted here, fails in the worker
    ids = upload(client, (tmp_path / "nobody.mp4").read_bytes()).json()
    res = client.post(f"/avatars/{ids['avatar_id']}/render", json={"pose": {"joints": {"x": [0, 0]}}})
    assert res.status_code == 422, res.text  # not 409 "still queued": the body was judged first


def test_health_counts_are_fresh_and_say_their_age(client, monkeypatch):
    from service.deps import JobCounts

    store = client.app.state.context.queue.store
    assert client.get("/healthz").json()["jobs"]["queued"] == 0
    time.sleep(JobCounts.max_age_s + 0.1)
    store.create({})  # the next poll sees it (the counts used to lag one poll behind)
    health = client.get("/healthz").json()
    assert health["jobs"]["queued"] == 1 and health["jobs_age_s"] < 0.5
    # A store too slow to answer: health answers at once with the last counts, and their age.
    monkeypatch.setattr(type(store), "counts", lambda self: time.sleep(2.0) or {"queued": 99})
    time.sleep(JobCounts.max_age_s + 0.1)
    t0 = time.perf_counter()
    health = client.get("/healthz").json()
    assert time.perf_counter() - t0 < 1.0 and health["jobs"]["queued"] == 1 and health["jobs_age_s"] > 1.0
