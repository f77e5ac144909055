"""Render requests under hostile values and load, in-process against a seeded avatar (no training):
physical bounds in the schema (1e300 is 422, not a blank 200), sizes checked before the avatar
loads, bounded dicts, one load for concurrent first requests, and the render gate (503 with
``Retry-After`` past its capacity)."""

from __future__ import annotations

import asyncio
import json
import threading

import httpx
import pytest
from fastapi.testclient import TestClient
from helpers.service import publish_seeded_avatar

from jobs import JobQueue, JobsConfig
from service import rendering as rendering_module
from service.app import create_app
from service.rendering import RenderBusy, RenderGate
from service.settings import ServiceSettings


def settings(tmp_path, **overrides) -> ServiceSettings:
    return ServiceSettings(jobs=JobsConfig(data_dir=tmp_path / "data"), preload_body_models=(), **overrides)


@pytest.fixture
def seeded(tmp_path, anny_model):
    """(app, avatar id) for an app whose queue holds one ready (seeded) avatar."""
    config = settings(tmp_path, max_render_pixels=256 * 256, max_render_side=512)
    queue = JobQueue(config.jobs)
    job = publish_seeded_avatar(queue, anny_model)
    app = create_app(config, queue=queue)
    app.state.context.avatars._bodies["anny"] = anny_model  # the session's model: no second load
    return app, job.output_id


@pytest.fixture
def client(seeded):
    app, _ = seeded
    with TestClient(app, base_url="http://127.0.0.1") as c:
        yield c


def render(client, avatar_id, body=None, raw: str | None = None):
    url = f"/avatars/{avatar_id}/render"
    if raw is not None:
        return client.post(url, content=raw, headers={"content-type": "application/json"})
    return client.post(url, json=body)


def test_a_seeded_avatar_renders(client, seeded):
    _, aid = seeded
    res = render(client, aid, {"pose": {"joints": {"upperarm01.L": [0, 0, -1]}}, "width": 64, "height": 64})
    assert res.status_code == 200 and res.content[:4] == b"\x89PNG", res.text
    assert render(client, aid, {"frame": 1}).status_code == 200  # the frames' own 64x96 size


def test_an_unreadable_quality_report_does_not_break_the_avatar(client, seeded, tmp_path):
    """avatar.json with a quality report the service cannot read (hand-edited, or a wrong type):
    the avatar is still listed and described, its quality null; a newer writer's extra keys are
    ignored."""
    _, aid = seeded
    meta = tmp_path / "data" / "avatars" / aid / "avatar.json"
    doc = json.loads(meta.read_text())
    doc["quality"] = {"held_out": {"split": "test_pose", "frames": "many"}}
    meta.write_text(json.dumps(doc))
    res = client.get(f"/avatars/{aid}")
    assert res.status_code == 200 and res.json()["quality"] is None
    newer = {"frames_kept": 3, "made_by": "a newer writer"}
    doc["quality"] = {"held_out": None, "detection": newer, "verdict": "good"}
    meta.write_text(json.dumps(doc))
    quality = client.get(f"/avatars/{aid}").json()["quality"]
    assert quality["detection"]["frames_kept"] == 3 and "made_by" not in quality["detection"]
    assert client.get("/avatars").status_code == 200


def test_a_render_beyond_the_training_range_says_so(client, seeded):
    """Trained on the rest pose from the front: a raised arm from the side is rendered all the
    same, and the X-Render-Warnings header (a JSON list) says what lies outside; [] inside."""
    _, aid = seeded
    inside = render(client, aid, {"width": 64, "height": 64})
    assert inside.status_code == 200 and json.loads(inside.headers["X-Render-Warnings"]) == []
    body = {
        "pose": {"joints": {"upperarm01.L": [0, 0, -1.2]}},
        "camera": {"yaw": 90},
        "width": 64,
        "height": 64,
    }
    beyond = render(client, aid, body)
    assert beyond.status_code == 200 and beyond.content[:4] == b"\x89PNG"
    warnings = json.loads(beyond.headers["X-Render-Warnings"])
    assert len(warnings) == 2 and "yaw 90 deg" in warnings[0] and "upperarm01.L" in warnings[1]
    assert json.loads(render(client, aid, {"frame": 1}).headers["X-Render-Warnings"]) == []


HUGE = [
    ('{"pose": {"transl": [1e300, 0, 0]}}', "transl"),
    ('{"pose": {"joints": {"upperarm01.L": [1e300, 0, 0]}}}', "joints"),
    ('{"pose": {"root_orient": [0, 0, 1e300]}}', "root_orient"),
    ('{"pose": {"joints": {"upperarm01.L": [5, 5, 0]}}}', "2 pi"),  # each < 2 pi, the norm is not
    ('{"pose": {"expression": {"jawOpen": 1e300}}}', "expression"),
    ('{"pose": {"shape": {"age": -1e300}}}', "shape"),
    ('{"camera": {"target": [0, 1e300, 0]}}', "target"),
    ('{"camera": {"distance": 1e300}}', "distance"),
    (
        '{"camera": {"K": [[1e300, 0, 32], [0, 1e300, 32], [0, 0, 1]], '
        '"viewmat": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]}}',
        "K",
    ),
    (
        '{"camera": {"K": [[50, 0, 32], [0, 50, 32], [0, 0, 1]], '
        '"viewmat": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1e300], [0, 0, 0, 1]]}}',
        "viewmat",
    ),
    ('{"width": 1e300}', "width"),
    ('{"frame": 1, "width": ' + "9" * 400 + "}", "width"),  # was a 500 (float overflow)
    ('{"frame": ' + "9" * 400 + "}", "frame"),
]


@pytest.mark.parametrize(("raw", "needle"), HUGE, ids=[f"{i}-{n}" for i, (_, n) in enumerate(HUGE)])
def test_out_of_range_values_are_422(client, seeded, raw, needle):
    _, aid = seeded
    res = render(client, aid, raw=raw)
    assert res.status_code == 422, res.text
    assert needle in res.text
    json.loads(res.text)


def test_expression_outside_the_models_range_is_422(client, seeded):
    _, aid = seeded
    res = render(client, aid, {"pose": {"expression": {"jawOpen": -0.5}}, "width": 64, "height": 64})
    assert res.status_code == 422 and "[0.0, 1.0]" in res.json()["detail"], res.text


def test_size_is_checked_before_the_avatar_loads(client, seeded):
    app, aid = seeded
    cache = app.state.context.avatars
    for body in ({"width": 512, "height": 512}, {"width": 600, "height": 16}, {"frame": 0, "width": 400}):
        res = render(client, aid, body)
        assert res.status_code == 422 and "limit" in res.json()["detail"], (body, res.text)
    assert cache.loads == 0  # refused from avatar.json and the request alone
    assert render(client, aid, {"width": 256, "height": 256}).status_code == 200
    assert cache.loads == 1


def test_huge_pose_dicts_are_refused_cheaply(client, seeded):
    _, aid = seeded
    many = {f"joint{i}": [0, 0, 0] for i in range(300)}  # over 256 keys, under the body limit
    res = render(client, aid, {"pose": {"joints": many}})
    assert res.status_code == 422 and "256" in res.text and len(res.content) < 4000, res.text[:500]
    huge = {f"j{i:06d}": [0, 0, 0] for i in range(20_000)}  # ~400 KB: over the JSON body limit
    res = render(client, aid, {"pose": {"joints": huge}})
    assert res.status_code == 413 and len(res.content) < 1000, res.text[:500]
    long_name = {"x" * 10_000: [0, 0, 0]}
    res = render(client, aid, {"pose": {"joints": long_name}})
    assert res.status_code == 422 and len(res.content) < 4000


def test_concurrent_first_requests_load_the_avatar_once(seeded, monkeypatch):
    app, aid = seeded
    ctx = app.state.context
    calls = []
    real = rendering_module.load_saved_avatar

    def counting(*args, **kwargs):
        calls.append(threading.get_ident())
        return real(*args, **kwargs)

    monkeypatch.setattr(rendering_module, "load_saved_avatar", counting)
    folder = ctx.queue.storage.avatar_dir(aid)
    results = []
    threads = [
        threading.Thread(target=lambda: results.append(ctx.avatars.get(aid, folder))) for _ in range(6)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and len(results) == 6 and all(r is results[0] for r in results)


def test_render_gate_runs_waits_and_refuses():
    async def scenario():
        gate = RenderGate(slots=1, waiting=1, wait_s=0.5)
        order: list[str] = []
        release = asyncio.Event()

        async def job(name: str):
            try:
                async with gate.slot():
                    order.append(f"start {name}")
                    await release.wait()
                    order.append(f"end {name}")
            except RenderBusy:
                order.append(f"busy {name}")

        first = asyncio.create_task(job("a"))
        await asyncio.sleep(0.01)
        second = asyncio.create_task(job("b"))  # waits
        await asyncio.sleep(0.01)
        await job("c")  # the line is full: refused at once
        assert gate.running == 1 and gate.queued == 1
        release.set()
        await asyncio.gather(first, second)
        assert order == ["start a", "busy c", "end a", "start b", "end b"]
        assert gate.running == 0 and gate.queued == 0
        # A waiter that gets no slot within wait_s is refused.
        release.clear()
        holder = asyncio.create_task(job("d"))
        await asyncio.sleep(0.01)
        await job("e")
        assert order[-1] == "busy e"
        release.set()
        await holder
        assert gate.running == 0

    asyncio.run(scenario())


def test_renders_past_the_gate_are_503_with_retry_after(tmp_path, anny_model):
    config = settings(tmp_path, max_renders=1, render_queue=1, render_wait_s=30.0)
    queue = JobQueue(config.jobs)
    job = publish_seeded_avatar(queue, anny_model)
    app = create_app(config, queue=queue)
    app.state.context.avatars._bodies["anny"] = anny_model

    async def burst():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as c:
            url, body = f"/avatars/{job.output_id}/render", {"width": 64, "height": 64}
            return await asyncio.gather(*[c.post(url, json=body) for _ in range(6)])

    answers = asyncio.run(burst())
    codes = sorted(r.status_code for r in answers)
    assert codes.count(200) >= 2 and codes.count(503) >= 1 and set(codes) <= {200, 503}, codes
    for r in answers:
        if r.status_code == 503:
            assert r.headers["retry-after"] == "1" and "busy" in r.json()["detail"]
