"""``eva demo``: the whole product on the embedded default, as a user would drive it.

A synthetic signer video (``eva_engine.demo.signer_video``) is uploaded to a real ``eva serve``
with a real ``eva worker`` (``service.local_stack``: both on a free loopback port, over a
private service folder); the job is followed to the end with its progress, then the avatar is rendered through
the API in a training frame's pose and in a new pose, framed as that frame's camera framed the
signer (``{"camera": {"frame": i}}``), from the front and turned 35 degrees. The PNG shows:
input frame | avatar in that frame's pose | new pose | new pose from 35 degrees. With
``out_mp4``, the avatar then performs a video of someone else (the synthetic signer with another
seed: another body, face and motion) through ``POST /avatars/{id}/animations``: the mp4 shows
that video beside the avatar.
"""

from __future__ import annotations

import io
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eva_engine.progress import Progress, ProgressEvent
from service.local_stack import LocalStack, LocalStackError


class DemoError(RuntimeError):
    """The service did not start or the job failed; the message says why."""


@dataclass
class DemoResult:
    """seconds: the whole run; phases: seconds per phase in the order they ran (the demo's own
    steps and each job stage as the service reports it, e.g. ``train``, ``animate render``)."""

    image: Path
    avatar_id: str
    seconds: float
    num_gaussians: int | None
    workdir: Path
    animation: Path | None = None
    phases: dict[str, float] = field(default_factory=dict)


class PhaseClock:
    """Wraps a progress callback: a phase lasts from its first report to the next phase's."""

    def __init__(self, progress: Progress | None) -> None:
        self.progress = progress or (lambda _: None)
        self.phases: dict[str, float] = {}
        self._current: str | None = None
        self._since = time.perf_counter()

    def __call__(self, event: ProgressEvent) -> None:
        if event.stage != self._current:
            self.stop()
            self._current, self._since = event.stage, time.perf_counter()
        self.progress(event)

    def stop(self) -> None:
        if self._current is not None:
            elapsed = time.perf_counter() - self._since
            self.phases[self._current] = self.phases.get(self._current, 0.0) + elapsed
        self._current = None


def run_service_demo(
    workdir: Path,
    out_png: Path,
    options: dict[str, str] | None = None,
    progress: Progress | None = None,
    timeout: float = 3600.0,
    out_mp4: Path | None = None,
) -> DemoResult:
    """Video -> service -> avatar -> renders (and, with ``out_mp4``, an animation; see the module
    docstring). ``options``: the upload form fields (``preset``, ``iterations``, ...; its
    ``fit_scale`` also applies to the driving video). Everything but the PNG and the mp4 goes
    under ``workdir`` (replaced on every run); the server and worker are stopped whatever
    happens."""
    import httpx
    from PIL import Image

    from eva_engine.body import load_body_model
    from eva_engine.demo import DEMO_POSE, signer_video

    started = time.perf_counter()
    workdir = Path(workdir)
    shutil.rmtree(workdir, ignore_errors=True)
    workdir.mkdir(parents=True)
    say = PhaseClock(progress)
    say(ProgressEvent("video"))
    video, frames = signer_video(workdir, load_body_model("anny"))

    try:
        stack = LocalStack(workdir / "service", logs=workdir)
    except LocalStackError as err:
        raise DemoError(str(err)) from err
    with stack:
        stack.start_server()
        stack.start_worker()
        with httpx.Client(base_url=stack.base_url, timeout=120.0) as api:
            say(ProgressEvent("service start"))
            try:
                stack.wait_healthy()
            except LocalStackError as err:
                raise DemoError(str(err)) from err
            with video.open("rb") as f:
                created = api.post(
                    "/avatars", files={"video": ("signer.mp4", f, "video/mp4")}, data=options or {}
                )
            _check(created, "upload")
            avatar_id, job_id = created.json()["avatar_id"], created.json()["job_id"]
            follow = _follower(api, stack, workdir, say, started + timeout)
            follow(job_id, "")
            info = _check(api.get(f"/avatars/{avatar_id}"), "avatar info").json()
            frame = info["num_frames"] // 2
            h, w = info["frame_size"]
            # The new pose is framed as the video framed the signer: that frame's camera, placed
            # where it was relative to the body, then turned 35 degrees about the body.
            requests = [
                {"frame": frame},
                {"pose": DEMO_POSE, "camera": {"frame": frame}},
                {"pose": DEMO_POSE, "camera": {"frame": frame, "yaw": 35.0}},
            ]
            panels = [(frames[frame].numpy() * 255 + 0.5).astype(np.uint8)]
            say(ProgressEvent("render"))
            for body in requests:
                png = _check(api.post(f"/avatars/{avatar_id}/render", json=body), "render").content
                panels.append(np.asarray(Image.open(io.BytesIO(png)).convert("RGB").resize((w, h))))
            if out_mp4 is not None:
                say(ProgressEvent("driving video"))
                driving, _ = signer_video(workdir / "driving", load_body_model("anny"), seed=1)
                form = {"camera": "front", "side_by_side": "true"}
                if options and options.get("fit_scale"):
                    form["fit_scale"] = options["fit_scale"]
                with driving.open("rb") as f:
                    created = api.post(
                        f"/avatars/{avatar_id}/animations",
                        data=form,
                        files={"video": ("someone_else.mp4", f, "video/mp4")},
                    )
                created = _check(created, "animation upload").json()
                follow(created["job_id"], "animate ")
                video = _check(api.get(f"/animations/{created['animation_id']}/video"), "animation").content
                out_mp4.parent.mkdir(parents=True, exist_ok=True)
                out_mp4.write_bytes(video)
    say.stop()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(panels, axis=1)).save(out_png)
    return DemoResult(
        out_png,
        avatar_id,
        time.perf_counter() - started,
        info.get("num_gaussians"),
        workdir,
        out_mp4,
        say.phases,
    )


def _follower(api, stack: LocalStack, workdir: Path, say: Progress, deadline: float):
    """follow(job_id, label): poll the job to its end, reporting progress; DemoError unless it
    succeeds."""

    def follow(job_id: str, label: str) -> None:
        while True:
            job = _check(api.get(f"/jobs/{job_id}"), "job status").json()
            stage = label + (job["stage"] or job["state"])
            say(ProgressEvent(stage, job["progress"], 1.0, job["message"], eta=job["eta_seconds"]))
            if job["state"] == "succeeded":
                return
            if job["state"] in ("failed", "cancelled"):
                raise DemoError(f"the {job['kind']} job {job['state']}: {job['error']} (logs in {workdir})")
            if time.perf_counter() > deadline or not stack.alive():
                raise DemoError(f"the job did not finish (logs in {workdir})")
            time.sleep(0.5)

    return follow


def _check(response, what: str):
    if response.status_code >= 400:
        raise DemoError(f"{what} failed: HTTP {response.status_code} {response.text[:300]}")
    return response
