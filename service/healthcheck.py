"""``python -m service.healthcheck``: the container's health, for either role of the image (the
Dockerfile's HEALTHCHECK). The role is read from the container's main process (PID 1): a worker
is healthy when it touched the file ``EVA_WORKER_HEALTH_FILE`` names within ``MAX_AGE_S`` seconds;
the API when ``/healthz`` answers 200 on ``EVA_PORT``. Exit status 0: healthy, 1: not (with the
reason)."""

from __future__ import annotations

import argparse
import os
import sys
import time
import urllib.request
from pathlib import Path

from jobs.worker import HEALTH_EVERY_S
from service.settings import ServiceSettings, env_name

MAX_AGE_S = 3 * HEALTH_EVERY_S
HEALTH_FILE_ENV = "EVA_WORKER_HEALTH_FILE"
"""The worker's health file (``eva worker --health-file``'s variable): no default, since a worker
started without it writes none."""


def container_role(cmdline: Path = Path("/proc/1/cmdline")) -> str:
    try:
        args = cmdline.read_bytes().split(b"\0")
    except OSError:
        return "api"
    return "worker" if b"worker" in args else "api"


def check_worker(health_file: Path, max_age: float = MAX_AGE_S) -> str | None:
    """None when healthy, else why not."""
    try:
        age = time.time() - health_file.stat().st_mtime
    except OSError:
        return f"no health file at {health_file} (is the worker running with --health-file?)"
    return None if age <= max_age else f"the worker last touched {health_file} {age:.0f} s ago"


def check_api(port: int, timeout: float = 4.0) -> str | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=timeout) as answer:
            return None if answer.status == 200 else f"/healthz answered {answer.status}"
    except OSError as err:
        return f"/healthz did not answer: {err}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--role", choices=("auto", "api", "worker"), default="auto")
    args = parser.parse_args(argv)
    role = container_role() if args.role == "auto" else args.role
    if role == "worker":
        path = os.environ.get(HEALTH_FILE_ENV)
        problem = (
            check_worker(Path(path))
            if path
            else f"{HEALTH_FILE_ENV} is not set, so the worker writes no health file to check"
        )
    else:
        port = ServiceSettings.model_fields["port"]
        problem = check_api(int(os.environ.get(env_name("port", port), port.default)))
    if problem:
        print(f"unhealthy ({role}): {problem}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
