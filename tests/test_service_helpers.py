"""Shared pieces of the service and job tests (imported by them; holds no tests): the tiny
synthetic signer video, and real ``eva serve`` / ``eva worker`` / ``redis-server`` processes on
loopback."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

EVA = str(Path(sys.executable).parent / "eva")
SIGNER_FRAMES = 4
# The pipeline at its smallest: 4 frames of 256 px, a few tiny-preset iterations at 1/4 scale.
FAST_OPTIONS = {"preset": "tiny", "iterations": "6", "image_scale": "0.25", "max_frames": str(SIGNER_FRAMES),
                "fit_scale": "0.1"}


@pytest.fixture(scope="session")
def signer_video(anny_model, tmp_path_factory) -> Path:
    """A short mp4 of the synthetic wild signer (256 px, MediaPipe finds the person); made once."""
    from eva_engine.data import load_dataset, write_video
    from eva_engine.data.synthetic import generate

    folder = tmp_path_factory.getbasetemp() / "service-signer"
    video = folder / "signer.mp4"
    if not video.is_file():
        folder.mkdir(exist_ok=True)
        ds = load_dataset(generate("wild", "small", 0, folder / "ds", model=anny_model))
        order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:SIGNER_FRAMES]
        frames = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
        write_video(folder / "partial.mp4", frames, fps=10)
        os.replace(folder / "partial.mp4", video)
    return video


@pytest.fixture(scope="session")
def other_signer_video(anny_model, tmp_path_factory) -> Path:
    """Someone else: 8 frames (2 fps) of the synthetic wild signer with seed 1 -- another body shape,
    face, clothes and motion than seed 0's (the demo's) -- at 256 px; made once."""
    from eva_engine.data import load_dataset, write_video
    from eva_engine.data.synthetic import generate

    folder = tmp_path_factory.getbasetemp() / "other-signer"
    video = folder / "someone_else.mp4"
    if not video.is_file():
        folder.mkdir(exist_ok=True)
        ds = load_dataset(generate("wild", "small", 1, folder / "ds", model=anny_model))
        order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:8]
        frames = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
        write_video(folder / "partial.mp4", frames, fps=ds.meta.fps)
        os.replace(folder / "partial.mp4", video)
    return video


def no_person_video(path: Path, frames: int = 3) -> Path:
    """A valid video of a grey gradient: decodes fine, holds nobody."""
    from eva_engine.data import write_video

    images = np.zeros((frames, 128, 128, 3), np.uint8)
    images[:] = np.linspace(0, 255, 128, dtype=np.uint8)[None, None, :, None]
    return write_video(path, images, fps=5)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate: Callable[[], object], timeout: float, what: str, every: float = 0.2):
    """Poll ``predicate`` until it returns something truthy; fail the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def start_process(args: list[str], log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("EVA_QUEUE_URL", None)
    with open(log, "ab") as out:
        return subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def start_worker(data_dir: Path, log: Path, queue_url: str | None = None, stale_after: float = 60.0):
    args = [EVA, "worker", "--data-dir", str(data_dir), "--threads", "1", "--stale-after", str(stale_after)]
    if queue_url:
        args += ["--queue-url", queue_url]
    return start_process(args, log)


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 20.0) -> None:
    """Stop a process we started (by its pid only)."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def log_tail(log: Path, chars: int = 3000) -> str:
    return log.read_text(errors="replace")[-chars:] if log.is_file() else "(no log)"
