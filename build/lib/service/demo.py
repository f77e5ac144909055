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
from service.client import ApiError, EvaClient, JobFailed
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
    from PIL import Image

    from eva_engine.body import load_body_model
    from eva_engine.demo import signer_video

    started = time.perf_counter()
    workdir = Path(workdir)
    shutil.rmtree(workdir, ignore_errors=True)
    workdir.mkdir(parents=True)
    say = PhaseClock(progress)
    say(ProgressEvent("video"))
    video, frames = signer_video(workdir, load_body_model("anny"))

    try:
        with LocalStack(workdir / "service", logs=workdir) as stack:
            stack.start_server()
            stack.start_worker()
            say(ProgressEvent("service start"))
            stack.wait_healthy()
            with EvaClient(stack.base_url) as api:
                panels, info = _avatar_and_renders(api, stack, video, frames, options, say, started + timeout)
                if out_mp4 is not None:
                    say(ProgressEvent("driving video"))
                    driving, _ = signer_video(workdir / "driving", load_body_model("anny"), seed=1)
                    form = {"camera": "front", "side_by_side": True}
                    if options and options.get("fit_scale"):
                        form["fit_scale"] = options["fit_scale"]
                    created = api.create_animation(info.avatar_id, driving, form)
                    api.wait(
                        created.job_id,
                        started + timeout - time.perf_counter(),
                        **_follow(say, stack, "animate "),
                    )
                    out_mp4.parent.mkdir(parents=True, exist_ok=True)
                    out_mp4.write_bytes(api.animation_video(created.animation_id))
    except (LocalStackError, ApiError, JobFailed, TimeoutError) as err:
        raise DemoError(f"{err} (logs in {workdir})") from err
    say.stop()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(panels, axis=1)).save(out_png)
    return DemoResult(
        out_png,
        info.avatar_id,
        time.perf_counter() - started,
        info.num_gaussians,
        workdir,
        out_mp4,
        say.phases,
    )


def _avatar_and_renders(
    api: EvaClient, stack: LocalStack, video: Path, frames, options, say, deadline: float
):
    """Upload ``video``, follow its job, render the three panels: (panels, the avatar's info)."""
    from PIL import Image

    from eva_engine.demo import DEMO_POSE

    created = api.create_avatar(video, options)
    api.wait(created.job_id, deadline - time.perf_counter(), **_follow(say, stack, ""))
    info = api.avatar(created.avatar_id)
    frame = info.num_frames // 2
    h, w = info.frame_size
    # The new pose is framed as the video framed the signer: that frame's camera, placed where it
    # was relative to the body, then turned 35 degrees about the body.
    requests = [
        {"frame": frame},
        {"pose": DEMO_POSE, "camera": {"frame": frame}},
        {"pose": DEMO_POSE, "camera": {"frame": frame, "yaw": 35.0}},
    ]
    panels = [(frames[frame].numpy() * 255 + 0.5).astype(np.uint8)]
    say(ProgressEvent("render"))
    for body in requests:
        png = api.render(info.avatar_id, body)
        panels.append(np.asarray(Image.open(io.BytesIO(png)).convert("RGB").resize((w, h))))
    return panels, info


def _follow(say: Progress, stack: LocalStack, label: str) -> dict:
    """``EvaClient.wait``'s keywords: each poll reported as progress, stopped when the stack dies."""

    def update(job) -> None:
        say(
            ProgressEvent(
                label + (job.stage or job.state), job.progress, 1.0, job.message, eta=job.eta_seconds
            )
        )

    return {"on_update": update, "alive": stack.alive}
