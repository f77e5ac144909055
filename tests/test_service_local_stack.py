"""``service.local_stack``: the serve + worker processes ``eva demo`` starts (the demo's test runs it
end to end); here, what a user sees when the stack cannot start, and that closing it leaves no
process behind."""

from __future__ import annotations

import socket
import time

import pytest

from service.local_stack import LocalStack, LocalStackError, free_port


def test_a_taken_port_is_a_clear_error_and_nothing_is_left_running(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with LocalStack(tmp_path / "service", logs=tmp_path / "logs", port=port) as stack:
            server = stack.start_server()
            with pytest.raises(LocalStackError, match="exited at start"):
                stack.wait_healthy(timeout=120)
            assert str(tmp_path / "logs") in str(stack.logs)
        assert server.poll() is not None
    assert (tmp_path / "logs" / "serve.log").read_text()  # the reason is in the log


def test_closing_the_stack_stops_its_server_and_workers(tmp_path):
    stack = LocalStack(tmp_path / "service", logs=tmp_path / "logs", port=free_port())
    stack.start_server()
    stack.start_worker("--threads", "1")
    # A worker of another host: a data dir of its own (bench/serving.py soak --hosts).
    stack.start_worker("--threads", "1", data_dir=tmp_path / "host-b")
    stack.wait_healthy(timeout=120)
    deadline = time.monotonic() + 120
    while not (tmp_path / "host-b" / "jobs").is_dir() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert (tmp_path / "host-b" / "jobs").is_dir()
    assert stack.alive() and len(stack.processes) == 3
    assert sorted(p.name for p in (tmp_path / "logs").iterdir()) == [
        "serve.log",
        "worker-2.log",
        "worker.log",
    ]
    stack.close()
    assert all(p.poll() is not None for p in stack.processes) and not stack.alive()
