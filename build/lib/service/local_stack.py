"""``LocalStack``: the service on this machine, as ``eva serve`` and ``eva worker`` processes on a
free loopback port sharing one data folder, each writing its own log; started, checked healthy
and stopped together. What ``eva demo``, the tests and the benchmarks start.

    with LocalStack(data_dir, logs=workdir) as stack:
        stack.start_server()
        stack.start_worker()
        stack.wait_healthy()
        httpx.get(f"{stack.base_url}/healthz")
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path


class LocalStackError(RuntimeError):
    """A process of the stack could not start, or exited, or the API did not answer."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (now)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def eva_executable() -> str:
    """The ``eva`` command beside this Python (the venv's), else on PATH."""
    local = Path(sys.executable).parent / "eva"
    found = str(local) if local.exists() else shutil.which("eva")
    if not found:
        raise LocalStackError("the `eva` command is not installed (run `make install`)")
    return found


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 20.0) -> None:
    """Stop a process this program started (by its pid only): ``sig``, then a kill after
    ``timeout`` seconds."""
    if proc.poll() is None:
        proc.send_signal(sig)
        _wait_or_kill(proc, timeout)


def launch(args: list[str], log: Path, env: dict[str, str] | None = None) -> subprocess.Popen:
    """Start ``args`` in a session of its own, appending its output to ``log``, with this
    process's environment unbuffered and without ``EVA_QUEUE_URL`` (a child names its queue), then
    ``env`` over it."""
    full = {**os.environ, "PYTHONUNBUFFERED": "1"}
    full.pop("EVA_QUEUE_URL", None)
    with open(log, "ab") as out:
        return subprocess.Popen(
            args, stdout=out, stderr=subprocess.STDOUT, env={**full, **(env or {})}, start_new_session=True
        )


def _wait_or_kill(proc: subprocess.Popen, timeout: float) -> None:
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class LocalStack:
    """data_dir: the service's folder (``EVA_SERVICE_DIR``); logs: the folder of the processes'
    logs (``serve.log``, ``worker.log``, ``worker-2.log`` ...); port: the API's (default: a free
    one); api_key: the API's key (none: loopback only); env: more environment for every process.
    The parent's ``EVA_QUEUE_URL`` is not passed on: the stack uses its own SQLite queue unless
    ``queue_url`` names one."""

    def __init__(
        self,
        data_dir: Path,
        logs: Path,
        port: int | None = None,
        api_key: str | None = None,
        queue_url: str | None = None,
        env: dict[str, str] | None = None,
        log_level: str = "warning",
    ) -> None:
        self.data_dir, self.logs = Path(data_dir), Path(logs)
        self.port = port or free_port()
        self.api_key, self.queue_url, self.log_level = api_key, queue_url, log_level
        self.extra_env = dict(env or {})
        self.server: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []
        self._eva = eva_executable()

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def headers(self) -> dict[str, str]:
        return {"X-API-Key": self.api_key} if self.api_key else {}

    def _start(self, args: list[str], log_name: str) -> subprocess.Popen:
        self.logs.mkdir(parents=True, exist_ok=True)
        if self.queue_url:
            args = [*args, "--queue-url", self.queue_url]
        env = {"EVA_API_KEY": self.api_key or "", "EVA_HOST": "127.0.0.1", **self.extra_env}
        return launch([self._eva, *args], self.logs / log_name, env)

    def start_server(self, *args: str) -> subprocess.Popen:
        """``eva serve`` on ``port`` (more options in ``args``)."""
        base = [
            "serve",
            "--port",
            str(self.port),
            "--data-dir",
            str(self.data_dir),
            "--log-level",
            self.log_level,
        ]
        self.server = self._start([*base, *args], "serve.log")
        return self.server

    def start_worker(self, *args: str, data_dir: Path | None = None) -> subprocess.Popen:
        """One more ``eva worker`` (more options in ``args``, e.g. ``--threads 1``); ``data_dir``:
        its own folder instead of the stack's (a worker on another host, sharing only the queue,
        records and storage that ``env`` names)."""
        name = "worker.log" if not self.workers else f"worker-{len(self.workers) + 1}.log"
        folder = self.data_dir if data_dir is None else Path(data_dir)
        worker = self._start(["worker", "--data-dir", str(folder), *args], name)
        self.workers.append(worker)
        return worker

    def wait_healthy(self, timeout: float = 180.0) -> None:
        """Until ``/healthz`` answers 200; ``LocalStackError`` (naming the logs) when a process
        of the stack exits first or ``timeout`` seconds pass."""
        import httpx

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            exited = [p for p in self.processes if p.poll() is not None]
            if exited:
                raise LocalStackError(f"the service or a worker exited at start (logs in {self.logs})")
            try:
                if httpx.get(f"{self.base_url}/healthz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.3)
        raise LocalStackError(f"the service did not answer within {timeout:.0f} s (logs in {self.logs})")

    @property
    def processes(self) -> list[subprocess.Popen]:
        return [p for p in (self.server, *self.workers) if p is not None]

    def alive(self) -> bool:
        """Whether every process of the stack is still running."""
        return all(p.poll() is None for p in self.processes)

    def close(self, timeout: float = 20.0) -> None:
        """Stop every process: SIGTERM to all at once (a worker stops now; its job is retried
        by the next worker), then each is waited for, killed after ``timeout`` seconds."""
        for p in self.processes:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.processes:
            _wait_or_kill(p, timeout)

    def __enter__(self) -> LocalStack:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
