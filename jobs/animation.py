"""Animation jobs: an existing avatar performs the motion of an uploaded driving video (or JSON pose
sequence), rendered to an mp4 (``eva_engine.animate``). Like avatar jobs, every stage's result
lands by an atomic rename, so a retried job starts after its last completed stage:

    work/<job_id>/input.<ext>      the upload: a video, or input.json (poses)
    work/<job_id>/dataset/         the driving video preprocessed and aligned (stages preprocess, align)
    work/<job_id>/animation/       animation.mp4 + animation.json (stage render)
    animations/<animation_id>/     the same folder, renamed (stage export)

The job record's ``avatar_id`` column holds the animation's id; ``options["avatar_id"]`` is the
avatar it animates (see ``jobs.store``).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field

from eva_engine.animate.animation import AnimationConfig

if TYPE_CHECKING:
    from jobs.pipeline import JobRun, Reporter
    from jobs.store import JobRecord

ANIMATION_STAGE_SPANS = {"preprocess": (0.0, 0.25), "align": (0.25, 0.45), "render": (0.45, 0.98),
                         "export": (0.98, 1.0)}  # fmt: skip
VIDEO_NAME, INFO_NAME = "animation.mp4", "animation.json"


class AnimationOptions(AnimationConfig):
    """What a user chooses for one animation: how it is rendered (``AnimationConfig``) and how a
    driving video is read -- max_frames (from the start), max_size (longest side, pixels),
    fit_scale (the body fit's iterations, 1 = the paper's). avatar_id: the avatar animated."""

    avatar_id: str = Field(..., pattern=r"^[0-9a-f]{32}$")
    max_frames: int = Field(300, ge=1, le=2000)
    max_size: int = Field(512, ge=64, le=2048)
    fit_scale: float = Field(1.0, gt=0.0, le=4.0)


def animation_stages(pipeline: JobRun, job: JobRecord, report: Reporter) -> None:
    """Run (or resume) animation job ``job`` in the job's process (``pipeline``: its ``JobRun``, with
    the storage and body models)."""
    from eva_engine.avatar import read_avatar_info
    from eva_engine.avatar.io import load_avatar

    options = AnimationOptions.model_validate(job.options)
    storage = pipeline.storage
    work = storage.work_dir(job.id)
    dataset_dir, rendered_dir = work / "dataset", work / "animation"
    animation_id = job.avatar_id
    if storage.animation_exists(animation_id):  # published before the last worker died
        return
    if not rendered_dir.is_dir():
        avatar_dir = storage.avatar_dir(options.avatar_id)
        if not avatar_dir.is_dir():
            raise FileNotFoundError(f"avatar {options.avatar_id} no longer exists")
        body = pipeline.body_model(read_avatar_info(avatar_dir)["body_model"])
        avatar = load_avatar(avatar_dir, body=body).eval()
        driving = _driving(work, dataset_dir, body, options, report)
        report.completed("align")
        _render(job, avatar, driving, options, rendered_dir, report)
    report.completed("render")
    report("export", 0.0, message="publishing the animation", force=True)
    storage.publish_animation(rendered_dir, animation_id)
    report.completed("export")


def _driving(work: Path, dataset_dir: Path, body, options: AnimationOptions, report: Reporter):
    from eva_engine.align import PreprocessConfig, preprocess_video, scaled_fit_config
    from eva_engine.animate import driving_from_dataset, driving_from_poses
    from eva_engine.animate.driving import DrivingError
    from jobs.pipeline import input_file

    upload = input_file(work)
    if dataset_dir.is_dir():  # aligned before the last worker died
        return driving_from_dataset(dataset_dir, body)
    if upload is None:
        raise FileNotFoundError("the uploaded driving video is missing from the job's folder")
    if upload.suffix == ".json":
        report("preprocess", 1.0, message="reading the poses", force=True)
        try:
            doc = json.loads(upload.read_text())
        except ValueError as err:
            raise DrivingError(f"the poses are not valid JSON: {err}") from err
        return driving_from_poses(doc, body)
    report("preprocess", 0.0, message="decoding the driving video", force=True)

    def progress(stage: str, done: int, total: int) -> None:
        frac = done / max(total, 1)
        if stage == "decode":
            report("preprocess", 0.1, message=f"decoded {done} frames")
        elif stage == "detect":
            report("preprocess", 0.1 + 0.9 * frac, message=f"detecting the person: frame {done}/{total}")
        elif stage == "align":
            report("align", 0.7 * frac, message="fitting the body model to the driving video", force=True)
        else:
            report("align", 0.7 + 0.3 * frac, message=f"writing frame {done}/{total}")

    config = PreprocessConfig(max_frames=options.max_frames, max_size=options.max_size,
                              fitting=scaled_fit_config(options.fit_scale))  # fmt: skip
    result = preprocess_video(upload, dataset_dir, config, model=body, progress=progress, overwrite=True)
    upload.unlink(missing_ok=True)  # the dataset holds the frames now
    return driving_from_dataset(dataset_dir, body, dropped=result.dropped_frames)


def _render(job: JobRecord, avatar, driving, options: AnimationOptions, out: Path, report: Reporter) -> None:
    from eva_engine.animate import animate, write_animation

    report("render", 0.0, message=f"rendering {len(driving)} driving frames", force=True)
    started = time.monotonic()

    def progress(done: int, total: int) -> None:
        elapsed = time.monotonic() - started
        eta = elapsed / done * (total - done) if done else None
        report("render", 0.95 * done / max(total, 1), eta=eta, message=f"rendering frame {done}/{total}")

    config = AnimationConfig.model_validate(options.model_dump(include=set(AnimationConfig.model_fields)))
    result = animate(avatar, driving, config, progress=progress)
    report("render", 0.95, message="encoding the video", force=True)
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    write_animation(partial / VIDEO_NAME, result)
    h, w = result.frames.shape[1:3]
    info = {
        "animation_id": job.avatar_id, "avatar_id": options.avatar_id, "job_id": job.id,
        "source": job.filename, "frames": len(result), "fps": result.fps, "width": w, "height": h,
        "duration_s": len(result) / result.fps, "driving_frames": len(driving),
        "driving_frames_without_person": driving.dropped, "options": options.model_dump(mode="json"),
        "render_seconds": time.monotonic() - started, "created_at": time.time(),
    }  # fmt: skip
    (partial / INFO_NAME).write_text(json.dumps(info, indent=2))
    os.replace(partial, out)


def read_animation_info(folder: Path) -> dict:
    """The ``animation.json`` of a published animation (empty if unreadable)."""
    try:
        return json.loads((folder / INFO_NAME).read_text())
    except (OSError, ValueError):
        return {}
