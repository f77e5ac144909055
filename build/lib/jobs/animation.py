"""Animation jobs: an existing avatar performs the motion of an uploaded driving video (or JSON pose
sequence), rendered to an mp4 (``eva_engine.animate``): the job kind ``ANIMATION``. They run like
avatar jobs (``jobs.avatar``), in the job's own process (``jobs.runner``, ``JobRun``), and
follow the same rules: every stage's result lands by an atomic rename, so a retried job starts
after its last completed stage; every record write is conditional on the attempt still owning
the job (``JobLost`` stops it otherwise, checked again before each result is put in place);
partial results carry the attempt's own suffix:

    work/<job_id>/input.video      the upload: a video (any container), or input.json (poses)
    work/<job_id>/dataset/         the driving video preprocessed and aligned (stages preprocess, align)
    work/<job_id>/animation/       animation.mp4 + animation.json (stage render)
    animations/<animation_id>/     the same folder, renamed (stage export)

The job record's ``output_id`` is the animation's id; ``options["avatar_id"]`` is the
avatar it animates (see ``jobs.store``). Its memory is bounded like an avatar job's: the driving
video's decoded frames, and the rendered frames (held until encoded), within
``JobsConfig.max_frame_pixels`` (``check_animation_budget``, at upload and again in the job).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from pydantic import Field

from eva_engine.progress import ProgressEvent
from eva_engine.specs.animation import AnimationConfig, AnimationError, output_frames, output_size
from jobs.options import MAX_FRAMES, MAX_SIZE, MIN_SIZE
from jobs.pipeline import JobKind, JobRun, Reporter
from jobs.progress import preprocess_progress
from jobs.store import JobRecord

logger = logging.getLogger("eva.jobs")

ANIMATION_STAGE_SPANS = {
    "preprocess": (0.0, 0.25),
    "align": (0.25, 0.45),
    "render": (0.45, 0.98),
    "export": (0.98, 1.0),
}
VIDEO_NAME, INFO_NAME = "animation.mp4", "animation.json"


class AnimationRequest(AnimationConfig):
    """What a user chooses for one animation: how it is rendered (``AnimationConfig``) and how a
    driving video is read -- max_frames (from the start), max_size (longest side, pixels),
    fit_scale (the body fit's iterations, 1 = the paper's)."""

    max_frames: int = Field(300, ge=1, le=MAX_FRAMES)
    max_size: int = Field(512, ge=MIN_SIZE, le=MAX_SIZE)
    fit_scale: float = Field(1.0, gt=0.0, le=4.0)


class AnimationOptions(AnimationRequest):
    """An animation job's options: what the user chose, and avatar_id, the avatar animated."""

    avatar_id: str = Field(..., pattern=r"^[0-9a-f]{32}$")


def animation_pixels(
    options: AnimationConfig,
    frames: int,
    fps: float,
    image_size: tuple[int, int] | None,
    span_s: float | None = None,
) -> tuple[int, int, int, int]:
    """(frames, width, height, pixels) of the animation of ``frames`` driving frames at ``fps``
    of ``image_size`` (height, width; None for poses), spanning ``span_s`` seconds if known
    (``output_frames``): what its rendered frames hold in memory until they are encoded (width
    includes the driving frame beside the avatar)."""
    count = output_frames(frames, fps, options, span_s)
    width, height = output_size(options, image_size)
    total = width
    if options.side_by_side and image_size is not None:
        total += max(1, round(image_size[1] * height / image_size[0]))
    return count, width, height, count * total * height


def check_animation_budget(
    options: AnimationConfig,
    frames: int,
    fps: float,
    image_size: tuple[int, int] | None,
    budget: int,
    span_s: float | None = None,
) -> None:
    """``AnimationError`` when the rendered frames would exceed ``budget`` pixels (arguments as
    ``animation_pixels``)."""
    count, width, height, pixels = animation_pixels(options, frames, fps, image_size, span_s)
    if pixels > budget:
        raise AnimationError(
            f"{count} frames of {width}x{height} pixels are {pixels / 1e6:.0f} M pixels; the limit is "
            f"{budget / 1e6:.0f} M: lower fps, width / height, or the number of driving frames"
        )


def animation_stages(run: JobRun, job: JobRecord, report: Reporter) -> None:
    """Run (or resume) animation job ``job`` in ``run`` (its storage, limits and body models)."""
    from eva_engine.avatar import load_avatar, read_avatar_meta

    options = AnimationOptions.model_validate(job.options)
    storage = run.storage
    animation_id = job.output_id
    if storage.animation_exists(animation_id):  # published before the last worker died
        return
    work = storage.fetch_upload(job.id)
    dataset_dir, rendered_dir = work / "dataset", work / "animation"
    if not rendered_dir.is_dir():
        avatar_dir = storage.avatar_dir(options.avatar_id)
        if not avatar_dir.is_dir():
            raise FileNotFoundError(f"avatar {options.avatar_id} no longer exists")
        body = run.body_model(read_avatar_meta(avatar_dir).body_model)
        avatar = load_avatar(avatar_dir, body=body).eval()
        driving = _driving(run, work, dataset_dir, body, options, report)
        report.completed("align")
        # Over the decoded frames' real time span: what will be rendered (the upload's check
        # could only count frames at the nominal rate, which a variable frame rate defeats).
        check_animation_budget(
            options,
            len(driving),
            driving.fps,
            driving.image_size,
            run.config.max_frame_pixels,
            span_s=driving.duration,
        )
        _render(run, job, avatar, driving, options, rendered_dir, report)
    report.completed("render")
    report(ProgressEvent("export", message="publishing the animation"), force=True)  # ownership checked here
    try:
        storage.publish_animation(rendered_dir, animation_id)
    except FileExistsError:  # another attempt published the same job's animation first
        logger.warning("job %s: animation %s was already published", job.id, animation_id)
    report.completed("export")


def _driving(run: JobRun, work: Path, dataset_dir: Path, body, options: AnimationOptions, report: Reporter):
    from eva_engine.align import PreprocessConfig, preprocess_video, scaled_fit_config
    from eva_engine.animate import driving_from_dataset, driving_from_poses
    from eva_engine.animate.driving import DrivingError
    from jobs.media import check_frame_budget, probe_video
    from jobs.storage import input_file, move_into_place

    upload = input_file(work)
    if dataset_dir.is_dir():  # aligned before the last worker died
        return driving_from_dataset(dataset_dir, body)
    if upload is None:
        raise FileNotFoundError("the uploaded driving video is missing from the job's folder")
    if upload.suffix == ".json":
        report(ProgressEvent("preprocess", 1, 1, "reading the poses"), force=True)
        try:
            doc = json.loads(upload.read_text())
        except ValueError as err:
            raise DrivingError(f"the poses are not valid JSON: {err}") from err
        return driving_from_poses(doc, body)
    report(ProgressEvent("preprocess", message="checking the driving video"), force=True)
    # Again here, not only at upload: the budget may have changed, and this is what decodes.
    info = probe_video(upload, run.config.max_video_side, decode_first=False)
    check_frame_budget(info, options.max_frames, options.max_size, run.config.max_frame_pixels)
    report(ProgressEvent("preprocess", message="decoding the driving video"), force=True)

    progress = preprocess_progress(report, fitted=" to the driving video")

    config = PreprocessConfig(
        max_frames=options.max_frames,
        max_size=options.max_size,
        fitting=scaled_fit_config(options.fit_scale),
        demuxer=info.container,  # decoded as what the probe approved
        max_video_side=run.config.max_video_side,
        face_crops=None,  # a driving video gives motion, not appearance
    )
    partial = dataset_dir.with_name(f"{dataset_dir.name}.partial-{run.attempt}")
    result = preprocess_video(upload, partial, config, model=body, progress=progress, overwrite=True)
    report(ProgressEvent("align", 1, 1, "driving video aligned"), force=True)  # still ours: put it in place
    move_into_place(partial, dataset_dir)
    upload.unlink(missing_ok=True)  # the dataset holds the frames now
    return driving_from_dataset(dataset_dir, body, dropped=result.dropped_frames)


def _render(
    run: JobRun, job: JobRecord, avatar, driving, options: AnimationOptions, out: Path, report: Reporter
) -> None:
    from eva_engine.animate import animate, write_animation
    from jobs.storage import move_into_place

    report(ProgressEvent("render", message=f"rendering {len(driving)} driving frames"), force=True)
    started = time.monotonic()

    def progress(event: ProgressEvent) -> None:  # the last 5%: encoding
        report(event.rescaled("render", 0.0, 0.95))

    config = AnimationConfig.model_validate(options.model_dump(include=set(AnimationConfig.model_fields)))
    result = animate(avatar, driving, config, progress=progress)
    report(ProgressEvent("render", 0.95, 1, "encoding the video"), force=True)
    partial = out.with_name(f"{out.name}.partial-{run.attempt}")
    partial.mkdir(parents=True)
    write_animation(partial / VIDEO_NAME, result)
    h, w = result.frames.shape[1:3]
    info = {
        "animation_id": job.output_id,
        "avatar_id": options.avatar_id,
        "job_id": job.id,
        "source": job.filename,
        "frames": len(result),
        "fps": result.fps,
        "width": w,
        "height": h,
        "duration_s": len(result) / result.fps,
        "driving_frames": len(driving),
        "driving_frames_without_person": driving.dropped,
        "options": options.model_dump(mode="json"),
        "render_seconds": time.monotonic() - started,
        "created_at": time.time(),
    }
    (partial / INFO_NAME).write_text(json.dumps(info, indent=2))
    report(ProgressEvent("render", 1, 1, "animation encoded"), force=True)  # still ours: put it in place
    move_into_place(partial, out)


def read_animation_info(folder: Path) -> dict:
    """The ``animation.json`` of a published animation (empty if unreadable)."""
    try:
        return json.loads((folder / INFO_NAME).read_text())
    except (OSError, ValueError):
        return {}


ANIMATION = JobKind(
    name="animation",
    output_field="animation_id",
    stage_spans=ANIMATION_STAGE_SPANS,
    options=AnimationOptions,
    run=animation_stages,
    input_fields=("avatar_id",),
)
