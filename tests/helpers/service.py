"""Shared pieces of the service and job tests (imported by them; holds no tests): the tiny
synthetic signer video, a seeded (untrained) published avatar, and real ``eva serve`` / ``eva
worker`` / ``redis-server`` / S3 (moto's server) / uvicorn processes on loopback."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from service.local_stack import eva_executable, free_port, launch, stop_process

stop = stop_process  # the tests' name for it
EVA = eva_executable()
SIGNER_FRAMES = 8
# The pipeline at its smallest: 8 frames of 256 px (the job keeps 4 out to score the avatar, 4
# train), a few tiny-preset iterations at 1/4 scale.
FAST_OPTIONS = {
    "preset": "tiny",
    "iterations": "6",
    "image_scale": "0.25",
    "max_frames": str(SIGNER_FRAMES),
    "fit_scale": "0.1",
}


@pytest.fixture(scope="session")
def signer_video(anny_model, tmp_path_factory) -> Path:
    """A short mp4 of the synthetic wild signer (256 px, MediaPipe finds the person); made once."""
    from eva_engine.data import load_dataset, write_video
    from eva_engine.synth import generate

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
    from eva_engine.synth import generate

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


def wait_for(predicate: Callable[[], object], timeout: float, what: str, every: float = 0.2):
    """Poll ``predicate`` until it returns something truthy; fail the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def start_process(args: list[str], log: Path, **env_extra: str) -> subprocess.Popen:
    return launch(args, log, env_extra)


def start_worker(data_dir: Path, log: Path, queue_url: str | None = None, stale_after: float = 60.0):
    args = [EVA, "worker", "--data-dir", str(data_dir), "--threads", "1", "--stale-after", str(stale_after)]
    if queue_url:
        args += ["--queue-url", queue_url]
    return start_process(args, log)


def finish_real_and_nobody(client, workers, logs: list[Path], real_job: str, nobody_job: str):
    """Wait for a signer job and a no-person job (ids) through ``client``, stop the ``workers``
    (whose logs are ``logs``), and check that the first succeeded and the second failed with its
    reason, each on its first attempt and run by exactly one worker; returns both jobs' states."""

    def finished(job_id):
        j = client.get(f"/jobs/{job_id}").json()
        return j["state"] in ("succeeded", "failed", "cancelled") and j

    try:
        first = wait_for(lambda: finished(real_job), 400, "the real job")
        second = wait_for(lambda: finished(nobody_job), 120, "the no-person job")
    finally:
        for w in workers:
            stop(w)
    text = "\n".join(log_tail(log) for log in logs)
    assert first["state"] == "succeeded" and first["attempts"] == 1, (first, text)
    assert second["state"] == "failed" and "no person" in second["error"], (second, text)
    ran = [sum(f"job {j['job_id']}: attempt" in log.read_text() for log in logs) for j in (first, second)]
    assert ran == [1, 1], text
    return first, second


def log_tail(log: Path, chars: int = 3000) -> str:
    return log.read_text(errors="replace")[-chars:] if log.is_file() else "(no log)"


def publish_seeded_avatar(queue, model, frames: int = 3, size: tuple[int, int] = (96, 64)):
    """A succeeded job whose avatar is a freshly seeded (untrained) Gaussian avatar with
    ``frames`` training frames of ``size`` (height, width) in the rest pose seen from the front,
    and their coverage, published the way a worker publishes one: the render and export
    endpoints work on it in milliseconds, without a training run."""
    import torch

    from eva_engine.avatar import Avatar, AvatarConfig, AvatarFrames, TrainingRecord, save_avatar
    from eva_engine.avatar.coverage import Coverage
    from eva_engine.render.camera import intrinsics, orbit_camera
    from jobs import JobOptions

    job = queue.store.create(JobOptions(preset="tiny").model_dump(), filename="seeded.mp4")
    worker = "tests:0:0:0:seeded"
    queue.store.update(job.id, state="running", worker=worker)
    config = AvatarConfig(init_max_gaussians=800, mlp_width=16, pe_frequencies=2, sh_degree=1)
    avatar = Avatar.create(model, model.shape_defaults, config)
    folder = queue.storage.avatar_dir(job.output_id)
    kept = AvatarFrames(
        params=model.default_params(frames),
        K=intrinsics(size[1], size[0], 40.0).expand(frames, 3, 3),
        viewmat=orbit_camera(0.0, 0.0, 2.6).float().expand(frames, 4, 4),
        timestamps=torch.arange(frames, dtype=torch.float64) / 10.0,
        image_size=size,
        fps=10.0,
    )
    record = TrainingRecord(coverage=Coverage.of_frames(model, kept.params, kept.viewmat))
    save_avatar(avatar, folder, record, frames=kept)
    assert queue.store.finish(job.id, "succeeded", owner=worker)
    return queue.store.get(job.id)


def run_job_here(queue, job_id: str, *models) -> str | None:
    """Claim the job and run it in this process, as its own process would (``jobs.runner``
    starts ``JobRun`` there), with already loaded body ``models``; returns its final state."""
    from jobs import JobRun, job_kind

    job = queue.store.claim(job_id, f"tests:0:{os.getpid()}:0:here")
    assert job is not None, f"job {job_id} could not be claimed"
    run = JobRun(queue.config, queue.store, queue.storage, job, job.worker, job_kind(job.kind))
    for model in models:
        run.add_body_model(model)
    return run.execute()


# The settings (the key among them) go through the environment, not the command line (ps shows it).
SERVE_CODE = (
    "import os; from service.settings import ServiceSettings; from service.server import serve; "
    "serve(ServiceSettings.model_validate_json(os.environ.pop('EVA_TEST_SETTINGS')), log_level='warning')"
)


def start_service(settings, log: Path) -> tuple[subprocess.Popen, str]:
    """A real uvicorn server (``service.server.serve``, as ``eva serve`` runs it) with ``settings``
    (a ``ServiceSettings``); returns the process and its base URL once ``/healthz`` answers."""
    import httpx

    secret_env = {"EVA_TEST_SETTINGS": settings.model_dump_json()}
    proc = start_process([sys.executable, "-c", SERVE_CODE], log, **secret_env)
    base = f"http://127.0.0.1:{settings.port}"

    def healthy():
        assert proc.poll() is None, log_tail(log)
        try:
            return httpx.get(f"{base}/healthz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    wait_for(healthy, 120, "the service to answer /healthz")
    return proc, base


def rss_mb(pid: int) -> float:
    """Resident memory of a process, MB (Linux)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(status.split("VmRSS:")[1].split()[0]) / 1024


HUGE_FRAME_CODE = """
import sys, av
from fractions import Fraction
side = int(sys.argv[2])
with av.open(sys.argv[1], "w") as out:
    stream = out.add_stream("libx264", rate=Fraction(1))
    stream.width = stream.height = side
    stream.pix_fmt = "yuv420p"
    stream.options = {"preset": "ultrafast"}
    frame = av.VideoFrame(side, side, "yuv420p")
    for plane in frame.planes:
        plane.update(bytes(plane.buffer_size))
    for packet in [*stream.encode(frame), *stream.encode()]:
        out.mux(packet)
"""


@pytest.fixture(scope="session")
def huge_frame_video(tmp_path_factory) -> Path:
    """A real 1-frame H.264 mp4 of 16000x16000 black pixels (a few tens of KB; decoding it takes
    ~1.2 GB). Encoded once, in a child process (~4 s, ~1.5 GB there)."""
    video = tmp_path_factory.getbasetemp() / "huge-frame" / "16k.mp4"
    if not video.is_file():
        video.parent.mkdir(exist_ok=True)
        partial = video.with_suffix(".partial.mp4")
        subprocess.run([sys.executable, "-c", HUGE_FRAME_CODE, str(partial), "16000"], check=True)
        os.replace(partial, video)
    return video


def gradient_video(path: Path, frames: int, side: int, fps: int = 10, live: bool = False) -> Path:
    """A fast-to-encode H.264 video of flat frames (``side`` x ``side``); ``live``: Matroska
    written as a stream, without duration or cues in its headers."""
    from fractions import Fraction

    import av

    options = {"live": "1"} if live else {}
    with av.open(str(path), "w", format="matroska" if live else None, container_options=options) as out:
        stream = out.add_stream("libx264", rate=Fraction(fps))
        stream.width = stream.height = side
        stream.pix_fmt = "yuv420p"
        stream.options = {"preset": "ultrafast"}
        for i in range(frames):
            frame = av.VideoFrame(side, side, "yuv420p")
            for plane, value in zip(frame.planes, (16 + 3 * i, 128, 128), strict=True):
                plane.update(bytes([value % 256]) * plane.buffer_size)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def job_processes(job_id: str | None = None) -> dict[int, str]:
    """pid -> job id of the running job processes (of ``job_id``, or all), not the helpers they fork."""
    from jobs.runner import job_processes as processes

    return {pid: p.job_id for pid, p in processes().items() if not p.forked and job_id in (None, p.job_id)}


def freeze_in_stage(client, job_id: str, stage: str, others: tuple[int, ...] = (), timeout: float = 300.0):
    """Stop (SIGSTOP) job ``job_id``'s process, with the processes ``others``, at a moment its
    record says it is running ``stage``, and return the stopped pids. The record is read again
    once they are stopped: a stopped job cannot leave its stage, so what the test does next
    happens in that stage however short it is (if it moved on in between, they are let go and
    the next moment is tried). A process stopped inside a write to the job store holds the
    SQLite lock, and the record cannot be read (the API answers 503): let go too, and tried again."""

    def status() -> dict | None:
        answer = client.get(f"/jobs/{job_id}")
        return answer.json() if answer.status_code == 200 else None

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pids = [*others, *job_processes(job_id)]
        job = status()
        if len(pids) > len(others) and job and job["state"] == "running" and job["stage"] == stage:
            for pid in pids:
                os.kill(pid, signal.SIGSTOP)
            job = status()
            if (
                job is not None
                and job["state"] == "running"
                and job["stage"] == stage
                and set(pids) <= {*others, *job_processes(job_id)}
            ):
                return pids
            for pid in pids:
                os.kill(pid, signal.SIGCONT)
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for job {job_id} in stage {stage!r}")


@pytest.fixture
def redis_url(tmp_path):
    """A real redis-server on a free loopback port, for this test only."""
    server = shutil.which("redis-server")
    if server is None:
        pytest.fail("redis-server is not installed (scripts/install-system-deps.sh installs it)")
    port = free_port()
    args = ["--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    subprocess.run([server, *args, "--dir", str(tmp_path), "--daemonize", "yes"], check=True)
    try:
        wait_for(
            lambda: (
                subprocess.run(["redis-cli", "-p", str(port), "ping"], capture_output=True).stdout.strip()
                == b"PONG"
            ),
            20,
            "redis-server",
        )
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        subprocess.run(["redis-cli", "-p", str(port), "shutdown", "nosave"], capture_output=True)


@pytest.fixture
def s3_bucket(tmp_path, monkeypatch) -> tuple[str, str]:
    """An S3-compatible server (moto's server mode, a real HTTP endpoint on loopback) with an empty
    bucket; returns (endpoint URL, ``s3://bucket/prefix``). The credentials are in this process's
    environment, so the workers it starts inherit them."""
    import boto3

    for name, value in (
        ("AWS_ACCESS_KEY_ID", "eva-test"),
        ("AWS_SECRET_ACCESS_KEY", "eva-test-secret"),
        ("AWS_DEFAULT_REGION", "us-east-1"),
    ):
        monkeypatch.setenv(name, value)
    port = free_port()
    log = tmp_path / "s3.log"
    proc = start_process([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)], log)
    endpoint = f"http://127.0.0.1:{port}"
    try:
        client = boto3.client("s3", endpoint_url=endpoint)

        def up():
            assert proc.poll() is None, log_tail(log)
            try:
                return client.list_buckets() is not None
            except Exception:
                return False

        wait_for(up, 60, "the S3 server")
        client.create_bucket(Bucket="eva-test")
        yield endpoint, "s3://eva-test/service"
    finally:
        stop(proc)
