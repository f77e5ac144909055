"""Animations: an avatar performs the motion of a driving video (or JSON poses), as a job; and the
pose controls a client builds sliders from. Thin: validation here, work in ``jobs.animation``.

The uploads meet the same guard as an avatar's video (``service.guard``: the key, the body limit
of uploads, uploads at once, stalled bodies) and the same checks before a job is queued, off the
event loop: the video's headers probed in a child process, its decoded frames and the rendered
frames within the job's pixel budget, the queue's quota; poses are parsed and checked against the
avatar's body model (at most ``max_poses_mb``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, BinaryIO

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Response, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from eva_engine.specs.animation import AnimationError
from jobs.animation import (
    VIDEO_NAME,
    AnimationOptions,
    animation_pixels,
    check_animation_budget,
    read_animation_info,
)
from jobs.store import JobRecord, new_id
from service.accounts import Caller
from service.animation_schemas import (
    AnimationCreated,
    AnimationForm,
    AnimationInfo,
    AnimationList,
    Framing,
    PoseControls,
)
from service.deps import (
    ServiceContext,
    animation_record,
    avatar_record,
    caller,
    check_job_quota,
    context,
    ready_avatar,
    render_admission,
)
from service.routers.responses import AVATAR_NOT_READY, BUSY, STILL_RUNNING, UPLOAD, error
from service.uploads import POSES_UPLOAD, VIDEO_UPLOAD, check_video, queued_job, save_upload

router = APIRouter(tags=["animations"])
NOT_FOUND = error(404, "Unknown or malformed id")


def _info(job: JobRecord, ctx: ServiceContext) -> AnimationInfo:
    folder = ctx.queue.storage.animation_dir(job.output_id)
    return AnimationInfo.of(job, read_animation_info(folder) if job.state == "succeeded" else None)


@router.post(
    "/avatars/{avatar_id}/animations",
    status_code=202,
    response_model=AnimationCreated,
    summary="Make the avatar perform a driving video (or JSON poses): queue an animation job",
    description="Upload `video` (anyone, any body proportions: it is preprocessed, aligned and "
    'retargeted onto the avatar) or `poses` (a JSON file `{"fps": 25, "poses": [BodyPose, ...]}`, '
    "applied as they are). Follow `GET /animations/{id}` (or the job) until `succeeded`, then download "
    "`video_url`. A video in which nobody is found fails its job with that reason.",
    responses={
        **NOT_FOUND,
        **AVATAR_NOT_READY,
        422: {
            "description": "No upload, not an mp4/mov/mkv/webm/avi video, too long or too large, bad "
            "poses or bad options"
        },
        **UPLOAD,
    },
)
async def create_animation(
    form: Annotated[AnimationForm, Form()],
    video: UploadFile | None = File(None, description="A driving video of one person (mp4, webm, ...)."),
    poses: UploadFile | None = File(None, description='Or a JSON pose sequence {"fps", "poses": [...]}.'),
    avatar: JobRecord = Depends(ready_avatar),
    ctx: ServiceContext = Depends(context),
    who: Caller = Depends(caller),
) -> AnimationCreated:
    options = AnimationOptions(**form.model_dump(), avatar_id=avatar.output_id)
    upload = _one_upload(video, poses)
    if poses is not None and (options.camera == "driving" or options.side_by_side):
        raise HTTPException(422, "camera 'driving' and side_by_side need a driving video, not poses")
    # File copies, the probe's child process, parsing poses and SQLite block: off the event loop.
    return await run_in_threadpool(
        _create, ctx, who, avatar, options, upload.file, upload.filename, poses is not None
    )


def _create(
    ctx: ServiceContext,
    who: Caller,
    avatar: JobRecord,
    options: AnimationOptions,
    source: BinaryIO,
    filename: str | None,
    is_poses: bool,
) -> AnimationCreated:
    queue, settings = ctx.queue, ctx.settings
    check_job_quota(ctx, who)
    animation_id = new_id()
    with queued_job(queue) as (job_id, work):
        # The worker tells poses from a video by the name: a video is never saved as .json.
        path = work / (POSES_UPLOAD if is_poses else VIDEO_UPLOAD)
        limit = settings.max_poses_bytes if is_poses else settings.max_upload_bytes
        if save_upload(source, path, limit) == 0:
            raise HTTPException(
                422, f"the uploaded {'poses are' if is_poses else 'video is'} empty (0 bytes)"
            )
        if is_poses:
            frames, fps, size = _check_poses(path, avatar, options, ctx)
        else:
            info = check_video(path, options, settings)
            scale = min(1.0, options.max_size / max(info.width, info.height))  # as preprocessing resizes
            size = (max(1, round(info.height * scale)), max(1, round(info.width * scale)))
            fps = info.fps or 25.0
            frames = min(options.max_frames, info.frame_count() or options.max_frames)
        _check_render_size(options, frames, fps, size, ctx)
        name = Path(filename or "upload").name[:200]
        queue.store.create(
            options.model_dump(mode="json"),
            filename=name,
            job_id=job_id,
            output_id=animation_id,
            kind="animation",
            account=who.account,
        )
    return AnimationCreated(animation_id=animation_id, job_id=job_id)


def _check_render_size(
    options: AnimationOptions, frames: int, fps: float, size: tuple[int, int] | None, ctx: ServiceContext
) -> None:
    """422 when one rendered frame is over the render limits (as for ``POST .../render``), or all
    of them over the job's pixel budget (they are held until encoded)."""
    settings = ctx.settings
    _, width, height, _ = animation_pixels(options, frames, fps, size)
    side, pixels = settings.max_render_side, settings.max_render_pixels
    if width > side or height > side or width * height > pixels:
        raise HTTPException(
            422,
            f"the animation's frames would be {width}x{height}, over the limit ({side} pixels a side, "
            f"{pixels} pixels in all); pass a smaller width / height",
        )
    try:
        check_animation_budget(options, frames, fps, size, settings.jobs.max_frame_pixels)
    except AnimationError as err:
        raise HTTPException(422, str(err)) from err


def _one_upload(video: UploadFile | None, poses: UploadFile | None) -> UploadFile:
    if video is None and poses is None:
        raise HTTPException(
            422,
            "no driving motion: upload a video (form field 'video') or a JSON pose "
            "sequence (form field 'poses')",
        )
    if video is not None and poses is not None:
        raise HTTPException(422, "upload a video or poses, not both")
    return video if video is not None else poses  # type: ignore[return-value]


def _check_poses(
    path: Path, avatar: JobRecord, options: AnimationOptions, ctx: ServiceContext
) -> tuple[int, float, None]:
    """422 unless the file is a pose sequence the avatar's body model understands (bounded
    values, known names, within the model's ranges) and its frames fit the render budget;
    returns (frames, fps, None: no image). The poses are counted before each is validated:
    validating is the costly part."""
    from eva_engine.animate import DrivingError, driving_from_poses
    from eva_engine.animate.driving import DEFAULT_POSES_FPS, MAX_POSES, MAX_POSES_FPS
    from eva_engine.avatar import read_avatar_meta

    try:
        doc = json.loads(path.read_bytes())
    except RecursionError as err:  # json's own limit on nesting, far deeper than a pose needs
        raise HTTPException(422, "the poses are nested too deeply to be a pose sequence") from err
    except (ValueError, UnicodeDecodeError) as err:
        raise HTTPException(422, f"the poses are not valid JSON: {err}") from err
    poses = doc if isinstance(doc, list) else doc.get("poses") if isinstance(doc, dict) else None
    fps = doc.get("fps", DEFAULT_POSES_FPS) if isinstance(doc, dict) else DEFAULT_POSES_FPS
    if isinstance(poses, list):
        if len(poses) > MAX_POSES:
            raise HTTPException(422, f"{len(poses)} poses: at most {MAX_POSES} in one animation")
        if isinstance(fps, int | float) and 0 < fps <= MAX_POSES_FPS:  # else validation says what is wrong
            _check_render_size(options, len(poses), float(fps), None, ctx)
    body = ctx.avatars.body(read_avatar_meta(ctx.queue.storage.avatar_dir(avatar.output_id)).body_model)
    try:
        driving = driving_from_poses(doc, body)
    except DrivingError as err:
        raise HTTPException(422, str(err)[:2000]) from err
    return len(driving), driving.fps, None


@router.get(
    "/animations/{animation_id}",
    response_model=AnimationInfo,
    responses=NOT_FOUND,
    summary="An animation's state and progress; its video's address once done",
)
def get_animation(job: JobRecord = Depends(animation_record), ctx: ServiceContext = Depends(context)):
    return _info(job, ctx)


@router.get(
    "/animations/{animation_id}/video",
    response_class=FileResponse,
    summary="The animation as an mp4 (H.264)",
    responses={
        200: {"content": {"video/mp4": {}}},
        **NOT_FOUND,
        **error(409, "The animation's job has not succeeded"),
    },
)
def animation_video(job: JobRecord = Depends(animation_record), ctx: ServiceContext = Depends(context)):
    file = ctx.queue.storage.animation_dir(job.output_id) / VIDEO_NAME
    if job.state != "succeeded" or not file.is_file():
        reason = job.error if job.state == "failed" else f"its job is {job.state}"
        raise HTTPException(409, f"animation {job.output_id} has no video: {reason}")
    return FileResponse(file, media_type="video/mp4", filename=f"animation-{job.output_id}.mp4")


@router.delete(
    "/animations/{animation_id}",
    status_code=204,
    summary="Delete an animation and its video",
    responses={**NOT_FOUND, **STILL_RUNNING},
)
def delete_animation(job: JobRecord = Depends(animation_record), ctx: ServiceContext = Depends(context)):
    if not job.finished:
        raise HTTPException(409, f"animation {job.output_id} is still being made; cancel job {job.id} first")
    ctx.queue.storage.delete_animation(job.output_id)
    ctx.queue.store.update(job.id, output_deleted=1)
    return Response(status_code=204)


@router.get(
    "/avatars/{avatar_id}/animations",
    response_model=AnimationList,
    responses=NOT_FOUND,
    summary="The animations of an avatar, oldest first",
)
def list_animations(
    avatar: JobRecord = Depends(avatar_record),
    ctx: ServiceContext = Depends(context),
    who: Caller = Depends(caller),
):
    jobs = ctx.queue.store.list(kind="animation", account=who.listed_account)
    jobs = [j for j in jobs if j.options.get("avatar_id") == avatar.output_id]
    return AnimationList(animations=[_info(j, ctx) for j in jobs])


@router.get(
    "/avatars/{avatar_id}/controls",
    response_model=PoseControls,
    responses={**NOT_FOUND, **AVATAR_NOT_READY, **BUSY},
    summary="Sliders for posing the avatar (joints, fingers, face) and a camera that frames it",
    description="Loading the avatar and posing its body cost like a render: this shares the render "
    "slots, and past them answers 503 with `Retry-After`.",
    dependencies=[Depends(render_admission)],  # first: a refusal costs no lookup
)
async def pose_controls(
    aspect: float = Query(1.0, gt=0.1, le=10.0, description="Width / height of the picture to frame."),
    avatar: JobRecord = Depends(ready_avatar),
    ctx: ServiceContext = Depends(context),
):
    async with ctx.renders.slot():
        return await run_in_threadpool(_controls, ctx, avatar, aspect)


def _controls(ctx: ServiceContext, avatar: JobRecord, aspect: float) -> PoseControls:
    from eva_engine.animate.controls import pose_controls as controls_of
    from eva_engine.avatar.framing import framing

    loaded = ctx.avatars.get(avatar.output_id, ctx.queue.storage.avatar_dir(avatar.output_id))
    with loaded.lock:
        controls = controls_of(loaded.avatar.body, loaded.avatar.shape)
        fit = framing(loaded.avatar, aspect=aspect)
    framed = Framing(target=fit.target, distance=fit.distance, fov_y=fit.fov_y)
    return PoseControls(body_model=loaded.avatar.body.name, controls=controls, framing=framed)
