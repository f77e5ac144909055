"""What a request meets before its endpoint, against a real uvicorn server: the key is checked
and the body capped before a byte of the body is read (measured: the server's memory and what
it accepted), uploads at once are capped, a stalled body is cut off, a blocked job store does
not stall ``/healthz``; and, in-process: docs behind the key, Host and cross-site checks, no
open API on a network address."""

from __future__ import annotations

import select
import socket
import sqlite3
import threading
import time

import httpx
import pytest
from fastapi.testclient import TestClient
from helpers import service as svc
from helpers.service import free_port, log_tail, rss_mb, start_service, stop
from typer.testing import CliRunner

from jobs import JobsConfig
from service import accounts as accounts_module
from service.app import create_app
from service.settings import ServiceSettings

KEY = "k3y-for-tests-0123456789"
signer_video = svc.signer_video  # a fixture


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A keyed server: 1 upload at once, bodies that stall for 1.5 s, or arrive slower than
    16 KB/s after 2 s, are cut off."""
    data = tmp_path_factory.mktemp("guarded")
    settings = ServiceSettings(
        jobs=JobsConfig(data_dir=data),
        port=free_port(),
        api_key=KEY,
        max_uploads=1,
        body_timeout_s=1.5,
        body_grace_s=2.0,
        preload_body_models=(),
        max_upload_mb=64,
    )
    log = data / "serve.log"
    proc, base = start_service(settings, log)
    try:
        yield proc, base, data, log
    finally:
        stop(proc)


UPLOAD_HEAD = {"Content-Type": "multipart/form-data; boundary=x", "X-API-Key": KEY}
PART = b'--x\r\nContent-Disposition: form-data; name="video"; filename="a.mp4"\r\n\r\n'


def push_body(
    base: str,
    path: str,
    length: int,
    headers: dict[str, str],
    chunk: int = 1 << 20,
    pause: float = 0.0,
    prefix: bytes = b"",
) -> tuple[int, int]:
    """Send a POST declaring ``length`` bytes: ``prefix``, then zeros until the server answers (or
    all is sent); returns (status code, bytes of body sent before the answer came)."""
    host, port = base.removeprefix("http://").split(":")
    head = [f"POST {path} HTTP/1.1", f"Host: {host}:{port}", f"Content-Length: {length}", "Connection: close"]
    head += [f"{k}: {v}" for k, v in headers.items()]
    sent = 0
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(("\r\n".join(head) + "\r\n\r\n").encode() + prefix)
        sent = len(prefix)
        block = b"\0" * chunk
        answer = b""
        while True:
            readable, _, _ = select.select([sock], [], [], 0)
            if readable or sent >= length:
                answer = sock.recv(4096)
                break
            try:
                sock.sendall(block[: min(chunk, length - sent)])
            except (BrokenPipeError, ConnectionResetError):
                answer = sock.recv(4096)
                break
            sent += min(chunk, length - sent)
            if pause:
                time.sleep(pause)
    return int(answer.split()[1]), sent


@pytest.mark.parametrize("path", ["/avatars/0123456789abcdef0123456789abcdef/render", "/avatars"])
def test_unauthenticated_oversized_body_is_refused_before_it_is_read(server, path):
    proc, base, _, log = server
    before = rss_mb(proc.pid)
    status, sent = push_body(base, path, 400 * 2**20, {"Content-Type": "application/json"})
    after = rss_mb(proc.pid)
    assert status == 401, log_tail(log)
    # Refused from the headers: at most what the socket buffers took before the answer came.
    assert sent < 16 * 2**20, sent
    assert after - before < 32, (before, after)  # was +810 MB (buffered whole, then 422)


def test_authenticated_bodies_over_their_limit_are_413_from_the_headers(server):
    proc, base, _, _ = server
    before = rss_mb(proc.pid)
    status, sent = push_body(
        base,
        "/avatars/0123456789abcdef0123456789abcdef/render",
        400 * 2**20,
        {"Content-Type": "application/json", "X-API-Key": KEY},
    )
    assert status == 413 and sent < 16 * 2**20
    status, sent = push_body(base, "/avatars", 400 * 2**20, UPLOAD_HEAD)
    assert status == 413 and sent < 16 * 2**20
    assert rss_mb(proc.pid) - before < 32

    def chunks():  # no Content-Length: cut off while streaming, after the 64 KB JSON limit
        for _ in range(64):
            yield b" " * 65536

    res = httpx.post(
        f"{base}/avatars/0123456789abcdef0123456789abcdef/render",
        content=chunks(),
        headers={"Content-Type": "application/json", "X-API-Key": KEY},
        timeout=30,
    )
    assert res.status_code == 413 and "64 KB" in res.json()["detail"]


def test_a_stalled_body_is_cut_off(server):
    _, base, _, _ = server
    started = time.monotonic()
    status, sent = push_body(base, "/avatars", 10 * 2**20, UPLOAD_HEAD, chunk=1024, pause=3.0, prefix=PART)
    assert status == 408 and sent <= 4096 and time.monotonic() - started < 10


def test_a_body_that_trickles_in_is_cut_off(server):
    """100 bytes a second never pauses long enough to stall, but would hold the upload slot for
    days: under 16 KB/s on average after the grace, the body is cut off with 408."""
    _, base, _, _ = server
    started = time.monotonic()
    status, sent = push_body(base, "/avatars", 10 * 2**20, UPLOAD_HEAD, chunk=100, pause=1.0, prefix=PART)
    took = time.monotonic() - started
    assert status == 408 and sent < 1000 and 2.0 <= took < 6.0, (status, sent, took)


def test_uploads_at_once_are_capped_with_retry_after(server):
    _, base, data, _ = server
    host, port = base.removeprefix("http://").split(":")
    slow = socket.create_connection((host, int(port)), timeout=30)
    try:  # one upload in progress (it sends slowly, within the stall limit)
        head = [f"POST /avatars HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Length: 100000\r\n"]
        head += [f"{k}: {v}\r\n" for k, v in UPLOAD_HEAD.items()]
        slow.sendall("".join(head).encode() + b"\r\n" + PART)
        time.sleep(0.5)
        res = httpx.post(
            f"{base}/avatars",
            headers={"X-API-Key": KEY},
            timeout=30,
            files={"video": ("a.mp4", b"\0" * 1000, "video/mp4")},
        )
        assert res.status_code == 503 and res.headers["retry-after"] == "1", res.text
        assert "retry" in res.json()["detail"]
    finally:
        slow.close()
    time.sleep(0.5)
    assert not list((data / "jobs" / "work").iterdir())


def test_healthz_answers_while_the_job_store_is_locked_during_an_upload(server, signer_video):
    _, base, data, _ = server
    db = sqlite3.connect(data / "jobs" / "jobs.db", timeout=5, isolation_level=None)
    db.execute("BEGIN EXCLUSIVE")  # another process holding a long write
    answers: list = []

    def upload():
        with open(signer_video, "rb") as f:
            files = {"video": ("s.mp4", f, "video/mp4")}
            res = httpx.post(f"{base}/avatars", headers={"X-API-Key": KEY}, files=files, timeout=60)
            answers.append(res)

    thread = threading.Thread(target=upload)
    thread.start()
    slowest = 0.0
    try:
        deadline = time.monotonic() + 3.0  # the upload waits on the lock meanwhile
        while time.monotonic() < deadline:
            t0 = time.perf_counter()
            assert httpx.get(f"{base}/healthz", timeout=10).status_code == 200
            slowest = max(slowest, time.perf_counter() - t0)
            time.sleep(0.05)
    finally:
        db.execute("ROLLBACK")
        db.close()
    thread.join(60)
    assert answers and answers[0].status_code == 202, answers and answers[0].text
    assert slowest < 0.5, slowest  # was: every request waited for the lock (the event loop was blocked)


# -- in-process ------------------------------------------------------------------------------------
def client(tmp_path, **overrides) -> TestClient:
    jobs = JobsConfig(data_dir=tmp_path / "data")
    settings = ServiceSettings(jobs=jobs, preload_body_models=(), **overrides)
    return TestClient(create_app(settings), base_url="http://127.0.0.1")


def test_docs_are_behind_the_key(tmp_path):
    with client(tmp_path, api_key=KEY) as c:
        for path in ("/docs", "/openapi.json", "/avatars"):
            assert c.get(path).status_code == 401, path
            assert c.get(path, headers={"X-API-Key": KEY}).status_code == 200, path
        assert c.get("/healthz").status_code == 200
        spec = c.get("/openapi.json", headers={"X-API-Key": KEY}).json()
        assert "APIKeyHeader" in spec["components"]["securitySchemes"]


def test_every_answer_carries_the_browser_defences(tmp_path):
    """nosniff, no framing by another site, and a content policy: the page runs only its own
    files; only the docs may load FastAPI's CDN."""
    with client(tmp_path, api_key=KEY) as c:
        answers = {
            "page": c.get("/"),
            "refusal": c.get("/avatars"),  # 401 from the guard
            "api": c.get("/avatars", headers={"X-API-Key": KEY}),
            "docs": c.get("/docs", headers={"X-API-Key": KEY}),
        }
    for name, res in answers.items():
        assert res.headers["X-Content-Type-Options"] == "nosniff", name
        assert res.headers["X-Frame-Options"] == "DENY", name
        assert "frame-ancestors 'none'" in res.headers["Content-Security-Policy"], name
    page = answers["page"].headers["Content-Security-Policy"]
    assert "default-src 'self'" in page and "unsafe-inline" not in page
    # The docs load Swagger UI from this service, no CDN: they work offline.
    docs = answers["docs"]
    assert "https:" not in docs.headers["Content-Security-Policy"] and "cdn." not in docs.text
    assert '<script src="/static/docs/swagger-ui-bundle.js">' in docs.text
    with client(tmp_path, api_key=KEY) as c:
        assert c.get("/static/docs/swagger-ui-bundle.js").status_code == 200  # public, like the page
        assert c.get("/redoc", headers={"X-API-Key": KEY}).status_code == 404


def test_the_key_is_compared_in_constant_time(tmp_path, monkeypatch):
    compared = []
    real = accounts_module.hmac.compare_digest

    def spy(a, b):
        compared.append((a, b))
        return real(a, b)

    monkeypatch.setattr(accounts_module.hmac, "compare_digest", spy)
    with client(tmp_path, api_key=KEY) as c:
        assert c.get("/avatars", headers={"X-API-Key": KEY[:-1] + "x"}).status_code == 401
        assert c.get("/avatars", headers={"X-API-Key": "é".encode()}).status_code == 401  # not ASCII
        assert c.get("/avatars", headers={"X-API-Key": KEY}).status_code == 200
    assert len(compared) == 3 and all(b == KEY.encode() for _, b in compared)


def test_foreign_host_headers_are_refused(tmp_path):
    with client(tmp_path) as c:  # loopback without a key: DNS rebinding would reach it by another name
        assert c.get("/avatars", headers={"Host": "attacker.example"}).status_code == 400
        assert c.get("/avatars", headers={"Host": "localhost:8000"}).status_code == 200
        assert c.get("/avatars").status_code == 200


def test_cross_site_writes_are_refused(tmp_path, signer_video):
    with client(tmp_path) as c:
        files = {"video": ("s.mp4", signer_video.read_bytes(), "video/mp4")}
        res = c.post("/avatars", files=files, headers={"Origin": "https://attacker.example"})
        assert res.status_code == 403 and "cross-site" in res.json()["detail"]
        assert c.post("/avatars", files=files, headers={"Sec-Fetch-Site": "cross-site"}).status_code == 403
        assert c.post("/avatars", files=files, headers={"Origin": "null"}).status_code == 403
        # Another program's page on another loopback port is another origin.
        for origin in (
            "http://127.0.0.1:3000",
            "http://localhost",
            "https://127.0.0.1",
            "http://127.0.0.1:x",
        ):
            res = c.post("/avatars", files=files, headers={"Origin": origin})
            assert res.status_code == 403, origin
        assert c.get("/avatars").json() == {"avatars": []}
        res = c.post("/avatars", files=files, headers={"Origin": "http://127.0.0.1"}, data={"preset": "tiny"})
        assert res.status_code == 202, res.text


def test_a_short_key_is_refused_and_the_key_stays_off_command_lines(tmp_path, monkeypatch):
    from jobs.child_env import child_environment
    from service.cli import app

    jobs = JobsConfig(data_dir=tmp_path / "data")
    with pytest.raises(ValueError, match="at least 16"):
        ServiceSettings(jobs=jobs, api_key="s3cret")
    result = CliRunner().invoke(app, ["serve", "--api-key", KEY, "--data-dir", str(tmp_path / "data")])
    assert result.exit_code == 2 and "No such option" in result.output
    short = tmp_path / "key"
    short.write_text("s3cret\n")
    result = CliRunner().invoke(app, ["serve", "--api-key-file", str(short), "--data-dir", str(tmp_path)])
    assert result.exit_code == 2 and "at least 16" in result.output
    # The children that read uploads (the probe, a job's process) never see the key.
    monkeypatch.setenv("EVA_API_KEY", KEY)
    monkeypatch.setenv("EVA_QUEUE_URL", "redis://:password@redis:6379/0")
    env = child_environment(EXTRA="1")
    assert "EVA_API_KEY" not in env and "EVA_QUEUE_URL" not in env and env["EXTRA"] == "1"


def test_no_open_api_on_a_network_address(tmp_path):
    jobs = JobsConfig(data_dir=tmp_path / "data")
    with pytest.raises(ValueError, match="without an API key"):
        ServiceSettings(jobs=jobs, host="0.0.0.0")
    assert ServiceSettings(jobs=jobs, host="0.0.0.0", api_key=KEY).trusted_hosts == ["*"]
    assert "127.0.0.1" in ServiceSettings(jobs=jobs, host="::1").trusted_hosts
    from service.cli import app

    result = CliRunner().invoke(
        app, ["serve", "--host", "0.0.0.0", "--data-dir", str(tmp_path / "data")], env={"EVA_API_KEY": ""}
    )
    assert result.exit_code == 2 and "without an API key" in result.output


def test_serve_lets_idle_openmp_threads_sleep_unless_told_otherwise(tmp_path, monkeypatch):
    """``eva serve`` sets OMP_WAIT_POLICY=PASSIVE before the server (and torch) loads; a value in
    the environment wins."""
    import os

    from service import server
    from service.cli import app

    seen = []

    def record(settings, log_level):
        seen.append(os.environ["OMP_WAIT_POLICY"])

    monkeypatch.setattr(server, "serve", record)
    monkeypatch.setenv("OMP_WAIT_POLICY", "")  # monkeypatch restores the variable as it was
    for given, expected in ((None, "PASSIVE"), ("ACTIVE", "ACTIVE")):
        if given is None:
            monkeypatch.delenv("OMP_WAIT_POLICY")
        else:
            monkeypatch.setenv("OMP_WAIT_POLICY", given)
        result = CliRunner().invoke(app, ["serve", "--data-dir", str(tmp_path)])
        assert result.exit_code == 0, result.output
        assert seen.pop() == expected


def test_the_container_health_check_reaches_the_api(server):
    from service import healthcheck

    _, base, _, _ = server
    assert healthcheck.check_api(int(base.rsplit(":", 1)[1])) is None  # /healthz needs no key
    assert "did not answer" in healthcheck.check_api(free_port())


def test_requests_in_flight_are_capped_but_health_answers(tmp_path):
    import asyncio

    jobs = JobsConfig(data_dir=tmp_path / "data")
    app = create_app(ServiceSettings(jobs=jobs, preload_body_models=(), max_requests=1))

    async def scenario():
        release = asyncio.Event()

        async def slow_body():  # an upload that holds the only slot until released
            yield b"--x\r\n"
            await release.wait()
            yield b"--x--\r\n"

        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as c:
            headers = {"content-type": "multipart/form-data; boundary=x"}
            held = asyncio.create_task(c.post("/avatars", content=slow_body(), headers=headers))
            await asyncio.sleep(0.2)
            busy, health = await c.get("/avatars"), await c.get("/healthz")
            release.set()
            await held
            return busy, health, await c.get("/avatars")

    busy, health, after = asyncio.run(scenario())
    assert busy.status_code == 503 and busy.headers["retry-after"] == "1", busy.text
    assert health.status_code == 200 and after.status_code == 200
