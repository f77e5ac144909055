"""Connections that never send a request cannot take the service down (``service.connections``),
against a real uvicorn server started as ``eva serve`` starts it: idle sockets are closed
oldest-first past a cap and after a header timeout, while ``/healthz`` and keyed requests answer;
a request in flight is not a waiting connection."""

from __future__ import annotations

import select
import socket
import time

import httpx
import pytest
from helpers.service import free_port, log_tail, start_service, stop

from jobs import JobsConfig
from service.connections import ConnectionLimits
from service.settings import ServiceSettings

KEY = "k3y-for-tests-0123456789"
HEADER_TIMEOUT, PER_CLIENT = 2.0, 16


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("connections")
    settings = ServiceSettings(
        jobs=JobsConfig(data_dir=data),
        port=free_port(),
        api_key=KEY,
        preload_body_models=(),
        connections=ConnectionLimits(header_timeout_s=HEADER_TIMEOUT, max_waiting_per_client=PER_CLIENT),
    )
    log = data / "serve.log"
    proc, base = start_service(settings, log)
    try:
        yield proc, base, log
    finally:
        stop(proc)


def address(base: str) -> tuple[str, int]:
    host, port = base.removeprefix("http://").split(":")
    return host, int(port)


def closed_by_server(sock: socket.socket) -> bool:
    """The server has closed ``sock`` (EOF or reset is waiting to be read)."""
    readable, _, _ = select.select([sock], [], [], 0)
    if not readable:
        return False
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


def timed_get(base: str, path: str, **headers) -> tuple[int, float]:
    start = time.monotonic()
    res = httpx.get(f"{base}{path}", headers=headers, timeout=10)
    return res.status_code, time.monotonic() - start


def test_200_idle_connections_leave_the_service_answering(server):
    proc, base, log = server
    idle = [socket.create_connection(address(base), timeout=5) for _ in range(200)]
    try:
        time.sleep(0.3)  # the server has seen them all
        assert timed_get(base, "/healthz")[0] == 200
        status, seconds = timed_get(base, "/avatars", **{"X-API-Key": KEY})
        assert status == 200 and seconds < 2.0, (status, seconds)
        status, seconds = timed_get(base, "/healthz")
        assert status == 200 and seconds < 2.0, (status, seconds)
        # The oldest went first: the newest PER_CLIENT of them are still open.
        closed = [closed_by_server(s) for s in idle]
        assert all(closed[: -PER_CLIENT - 2]) and not any(closed[-PER_CLIENT + 2 :]), closed
        assert proc.poll() is None, log_tail(log)
    finally:
        for s in idle:
            s.close()


def test_headers_that_never_finish_are_cut_off_after_the_timeout(server):
    _, base, _ = server
    with socket.create_connection(address(base), timeout=5) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\n")
        start = time.monotonic()
        cut = None
        while time.monotonic() - start < 3 * HEADER_TIMEOUT:
            try:  # a slow sender: a byte of header every 0.25 s, never the end
                sock.sendall(b"X")
            except (BrokenPipeError, ConnectionResetError):
                cut = time.monotonic() - start
                break
            if closed_by_server(sock):
                cut = time.monotonic() - start
                break
            time.sleep(0.25)
    assert cut is not None and HEADER_TIMEOUT - 0.3 < cut < HEADER_TIMEOUT + 1.0, cut


def test_a_connection_with_a_request_in_flight_is_not_waiting(server):
    """A body that streams slowly (within ``body_timeout_s``) is past its headers: the header
    timeout and the caps leave it alone, and it gets its answer."""
    _, base, _ = server
    host, port = address(base)
    body = b'{"yaw": 0.5}'
    head = (
        f"POST /avatars/{'0' * 32}/render HTTP/1.1\r\nHost: {host}:{port}\r\nX-API-Key: {KEY}\r\n"
        f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    with socket.create_connection((host, port), timeout=10) as sock:
        sock.sendall(head.encode())
        time.sleep(0.3)  # the server has read the headers (until then it is a waiting connection)
        others = [socket.create_connection((host, port), timeout=5) for _ in range(2 * PER_CLIENT)]
        try:
            for byte in body:  # 12 bytes over 3 s: past the header timeout
                time.sleep(3 * HEADER_TIMEOUT / 2 / len(body))
                sock.sendall(bytes([byte]))
            answer = sock.recv(4096)
        finally:
            for s in others:
                s.close()
    assert answer.split()[1] == b"404", answer  # the avatar is unknown: it was answered
