"""``service.client.EvaClient``: the API's answers as its own schemas, its refusals as ``ApiError``
with the status and the reason, a failed job as ``JobFailed`` (in process, over FastAPI's test
client; ``eva demo``'s test drives it against real processes)."""

from __future__ import annotations

import io

import pytest
from fastapi.testclient import TestClient
from helpers.service import publish_seeded_avatar
from PIL import Image

from jobs.config import JobsConfig
from jobs.queue import JobQueue
from service.app import create_app
from service.client import ApiError, EvaClient, JobFailed, form_fields
from service.schemas import AvatarInfo, JobInfo
from service.settings import ServiceSettings


@pytest.fixture
def api(tmp_path, anny_model):
    config = ServiceSettings(jobs=JobsConfig(data_dir=tmp_path / "data"), preload_body_models=())
    queue = JobQueue(config.jobs)
    job = publish_seeded_avatar(queue, anny_model)
    failed = queue.store.create({"preset": "tiny"}, filename="nobody.mp4")
    queue.store.update(failed.id, state="running", worker="tests:0:0:0:x")
    queue.store.finish(failed.id, "failed", error="no person was found in the video", owner="tests:0:0:0:x")
    app = create_app(config, queue=queue)
    app.state.context.avatars._bodies["anny"] = anny_model
    with TestClient(app, base_url="http://127.0.0.1") as http, EvaClient(http=http) as client:
        yield client, job, failed


def test_answers_come_back_typed(api):
    client, job, _ = api
    assert client.health().status == "ok"
    info = client.avatar(job.output_id)
    assert isinstance(info, AvatarInfo) and info.status == "ready" and info.num_gaussians > 0
    done = client.wait(job.id, timeout=10)
    assert isinstance(done, JobInfo) and done.state == "succeeded" and done.avatar_id == job.output_id
    png = client.render(job.output_id, {"width": 64, "height": 48, "camera": "left"})
    assert Image.open(io.BytesIO(png)).size == (64, 48)


def test_refusals_and_failures_carry_the_reason(api):
    client, job, failed = api
    with pytest.raises(ApiError) as err:
        client.avatar("0" * 32)
    assert err.value.status == 404 and "no avatar" in err.value.detail
    with pytest.raises(ApiError) as err:
        client.render(job.output_id, {"width": 10})
    assert err.value.status == 422 and "width" in err.value.detail
    with pytest.raises(JobFailed, match="no person was found") as failure:
        client.wait(failed.id, timeout=10)
    assert failure.value.job.state == "failed"


def test_form_fields_spell_values_as_the_form_reads_them():
    assert form_fields({"preset": "fast", "side_by_side": True, "fit_scale": 0.5, "x": False}) == {
        "preset": "fast",
        "side_by_side": "true",
        "fit_scale": "0.5",
        "x": "false",
    }
    assert form_fields(None) == {}
