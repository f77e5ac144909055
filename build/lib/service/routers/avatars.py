from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, BinaryIO, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Response, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from pydantic import ValidationError

from eva_engine.avatar import read_avatar_meta
from eva_engine.avatar.render_spec import coverage_warnings, frame_params, spec_camera, spec_params
from jobs.options import JobOptions
from jobs.store import JobRecord, new_id
from service import rendering
from service.accounts import Caller
from service.deps import (
    ServiceContext,
    avatar_record,
    caller,
    check_job_quota,
    check_ready,
    context,
    ready_avatar,
    render_admission,
)
from service.routers.responses import AVATAR_NOT_READY, BUSY, STILL_RUNNING, UPLOAD, error
from service.schemas import AvatarCreated, AvatarForm, AvatarInfo, AvatarList, QualityReport, RenderRequest
from service.uploads import VIDEO_UPLOAD, check_video, queued_job, save_upload

router = APIRouter(prefix="/avatars", tags=["avatars"])
logger = logging.getLogger("eva.service")
WARNINGS_HEADER = "X-Render-Warnings"
NOT_FOUND = error(404, "Unknown or malformed avatar id")


@router.post(
    "",
    status_code=202,
    response_model=AvatarCreated,
    summary="Upload a video of one person; queue the job that learns their avatar",
    responses={
        422: {
            "description": "Not an mp4/mov/mkv/webm/avi video, no decodable frame, too long or too large, "
            "or bad options"
        },
        **UPLOAD,
    },
)
async def create_avatar(
    video: Annotated[UploadFile, File(description="A video of one person (mp4, mov, mkv, webm or avi).")],
    options: Annotated[AvatarForm, Form()],
    ctx: ServiceContext = Depends(context),
    who: Caller = Depends(caller),
) -> AvatarCreated:
    # File copies, the probe's child process and SQLite block: off the event loop.
    return await run_in_threadpool(_create, ctx, who, options, video.file, video.filename)


def _create(
    ctx: ServiceContext, who: Caller, options: JobOptions, source: BinaryIO, filename: str | None
) -> AvatarCreated:
    queue, settings = ctx.queue, ctx.settings
    check_job_quota(ctx, who)
    avatar_id = new_id()
    with queued_job(queue) as (job_id, work):
        path = work / VIDEO_UPLOAD
        if save_upload(source, path, settings.max_upload_bytes) == 0:
            raise HTTPException(422, "the uploaded video is empty (0 bytes)")
        check_video(path, options, settings)
        name = Path(filename or "video").name[:200]
        queue.store.create(
            options.model_dump(), filename=name, job_id=job_id, output_id=avatar_id, account=who.account
        )
    return AvatarCreated(avatar_id=avatar_id, job_id=job_id)


def _quality(doc: dict | None, avatar_id: str) -> QualityReport | None:
    """``avatar.json``'s quality report; None when absent, or unreadable (logged: the avatar still
    serves)."""
    if not doc:
        return None
    try:
        return QualityReport.model_validate(doc)
    except ValidationError as err:
        logger.warning("avatar %s: unreadable quality report: %s", avatar_id, err)
        return None


def _info(job: JobRecord, ctx: ServiceContext) -> AvatarInfo:
    status = {"queued": "pending", "running": "pending", "succeeded": "ready"}.get(job.state, job.state)
    info = AvatarInfo(
        avatar_id=job.output_id,
        job_id=job.id,
        status=status,  # type: ignore[arg-type]
        created_at=job.created_at,
        source_video=job.filename,
        error=job.error,
        preset=job.options.get("preset"),
        body_model=job.options.get("body_model"),
    )
    if status == "ready" and ctx.queue.storage.avatar_exists(job.output_id):
        meta = read_avatar_meta(ctx.queue.storage.avatar_dir(job.output_id))
        info = info.model_copy(
            update={
                "body_model": meta.body_model,
                "num_gaussians": meta.num_gaussians,
                "iterations": meta.iterations,
                "train_seconds": meta.train_seconds,
                "final_loss": meta.final_loss,
                "metrics": meta.metrics,
                "quality": _quality(meta.quality, job.output_id),
                "num_frames": meta.frames.count if meta.frames else None,
                "frame_size": meta.frames.image_size if meta.frames else None,
            }
        )
    return info


@router.get("", response_model=AvatarList, summary="All avatars (with accounts: the caller's), oldest first")
def list_avatars(ctx: ServiceContext = Depends(context), who: Caller = Depends(caller)) -> AvatarList:
    jobs = ctx.queue.store.list(kind="avatar", account=who.listed_account)
    return AvatarList(avatars=[_info(job, ctx) for job in jobs])


@router.get("/{avatar_id}", response_model=AvatarInfo, responses=NOT_FOUND, summary="An avatar's metadata")
def get_avatar(job: JobRecord = Depends(avatar_record), ctx: ServiceContext = Depends(context)) -> AvatarInfo:
    return _info(job, ctx)


@router.delete(
    "/{avatar_id}",
    status_code=204,
    responses={**NOT_FOUND, **STILL_RUNNING},
    summary="Delete an avatar and its files",
)
def delete_avatar(
    job: JobRecord = Depends(avatar_record), ctx: ServiceContext = Depends(context)
) -> Response:
    if not job.finished:
        raise HTTPException(409, f"avatar {job.output_id} is still being made; cancel job {job.id} first")
    ctx.queue.storage.delete_avatar(job.output_id)
    ctx.queue.store.update(job.id, output_deleted=1)
    ctx.avatars.forget(job.output_id)
    return Response(status_code=204)


@router.post(
    "/{avatar_id}/render",
    response_class=Response,
    summary="Render the avatar in a pose, expression and view",
    description="The body is the request's `pose` (or training frame `frame`), seen through `camera`; "
    "the answer is the image's bytes (PNG or JPEG). A pose or view beyond what the training video "
    f"showed is still rendered; the header `{WARNINGS_HEADER}` (a JSON list of sentences, empty when "
    "none) says what lies outside it. At most a few renders run at once: past them, 503 with "
    "`Retry-After`.",
    responses={
        200: {
            "content": {"image/png": {}, "image/jpeg": {}},
            "description": "The rendered image",
            "headers": {
                WARNINGS_HEADER: {
                    "description": "JSON list: what the request asks for beyond the training range "
                    "(camera yaw or pitch, joints, facial actions); [] when it stays inside",
                    "schema": {"type": "string"},
                }
            },
        },
        **NOT_FOUND,
        **AVATAR_NOT_READY,
        **BUSY,
        422: {"description": "Unknown names, values out of range, wrong lengths, size over the limit"},
    },
    dependencies=[Depends(render_admission)],  # first: a refusal costs no validation or lookup
)
async def render_avatar(
    req: RenderRequest | None = None,
    job: JobRecord = Depends(avatar_record),
    ctx: ServiceContext = Depends(context),
) -> Response:
    # Here, not as a dependency: a malformed body is a 422 whatever the avatar's state.
    await run_in_threadpool(check_ready, job, ctx)
    req = req or RenderRequest()
    folder = ctx.queue.storage.avatar_dir(job.output_id)
    limits = ctx.settings.max_render_side, ctx.settings.max_render_pixels
    width, height = await run_in_threadpool(rendering.checked_size, req, folder, *limits)  # before loading
    async with ctx.renders.slot():
        data, warnings = await run_in_threadpool(_render, ctx, job.output_id, folder, req, width, height)
    media_type = "image/png" if req.format == "png" else "image/jpeg"
    return Response(data, media_type=media_type, headers={WARNINGS_HEADER: json.dumps(warnings)})


def _render(
    ctx: ServiceContext, avatar_id: str, folder: Path, req: RenderRequest, width: int, height: int
) -> tuple[bytes, list[str]]:
    loaded = ctx.avatars.get(avatar_id, folder)
    params = spec_params(loaded.avatar, req, loaded.frames)  # checked against the body model's ranges
    camera = spec_camera(req, width, height, loaded.frames, loaded.avatar, params)
    image = rendering.render_image(loaded, params, camera, req.background)
    warnings = coverage_warnings(loaded.coverage, loaded.avatar, req, params, camera)
    return rendering.encode_image(image, req.format), warnings


@router.get(
    "/{avatar_id}/export",
    response_class=Response,
    summary="Download the avatar: the 3D Gaussians (PLY) or the posed body mesh (GLB)",
    responses={
        200: {"content": {"application/octet-stream": {}, "model/gltf-binary": {}}},
        **NOT_FOUND,
        **AVATAR_NOT_READY,
        **BUSY,
    },
)
async def export_avatar(
    format: Literal["ply", "glb"] = Query("ply", description="ply: 3DGS splats (rest pose); glb: mesh"),
    frame: int | None = Query(
        None, ge=0, le=100_000, description="glb: pose of this training frame (default rest)"
    ),
    job: JobRecord = Depends(ready_avatar),
    ctx: ServiceContext = Depends(context),
) -> Response:
    folder = ctx.queue.storage.avatar_dir(job.output_id)
    if format == "ply":
        if frame is not None:
            raise HTTPException(422, "'frame' applies to format=glb only (the PLY is the rest pose)")
        from eva_engine.avatar.io import PLY_NAME

        return FileResponse(
            folder / PLY_NAME, media_type="application/octet-stream", filename=f"avatar-{job.output_id}.ply"
        )
    async with ctx.renders.slot():  # posing the mesh costs like a render
        data = await run_in_threadpool(_glb, ctx, job.output_id, folder, frame)
    disposition = f'attachment; filename="avatar-{job.output_id}.glb"'
    return Response(data, media_type="model/gltf-binary", headers={"Content-Disposition": disposition})


def _glb(ctx: ServiceContext, avatar_id: str, folder: Path, frame: int | None) -> bytes:
    loaded = ctx.avatars.get(avatar_id, folder)
    params = frame_params(loaded.frames, frame) if frame is not None else rendering.rest_params(loaded)
    return rendering.posed_mesh_glb(loaded, params)
