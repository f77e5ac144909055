"""Request dependencies: the app's context and ids resolved to records (404s). The API key is
checked before routing, by ``service.guard``."""

from __future__ import annotations

from dataclasses import dataclass

from fastapi import Depends, HTTPException, Request

from jobs.queue import JobQueue
from jobs.store import JobRecord, is_valid_id
from service.rendering import AvatarCache, RenderGate
from service.settings import ServiceSettings


@dataclass
class ServiceContext:
    """Everything a request needs, held by the app (no module-level state)."""

    settings: ServiceSettings
    queue: JobQueue
    avatars: AvatarCache
    renders: RenderGate


def context(request: Request) -> ServiceContext:
    return request.app.state.context


def _check_id(value: str, what: str) -> None:
    if not is_valid_id(value):
        raise HTTPException(404, f"no {what} with id {value!r} (ids are 32 lowercase hex characters)")


def job_record(job_id: str, ctx: ServiceContext = Depends(context)) -> JobRecord:
    _check_id(job_id, "job")
    job = ctx.queue.store.get(job_id)
    if job is None:
        raise HTTPException(404, f"no job with id {job_id!r}")
    return job


def avatar_record(avatar_id: str, ctx: ServiceContext = Depends(context)) -> JobRecord:
    """The job record behind an avatar (one job makes one avatar)."""
    _check_id(avatar_id, "avatar")
    job = ctx.queue.store.by_avatar(avatar_id)
    if job is None:
        raise HTTPException(404, f"no avatar with id {avatar_id!r}")
    return job


def ready_avatar(
    job: JobRecord = Depends(avatar_record), ctx: ServiceContext = Depends(context)
) -> JobRecord:
    """409 unless the avatar is finished and on disk."""
    if job.state != "succeeded":
        reason = {
            "queued": "its job is queued",
            "running": f"its job is running (stage {job.stage})",
            "failed": f"its job failed: {job.error}",
            "cancelled": "its job was cancelled",
        }[job.state]
        raise HTTPException(409, f"avatar {job.avatar_id} is not ready: {reason}")
    if not ctx.queue.storage.avatar_exists(job.avatar_id):
        raise HTTPException(409, f"avatar {job.avatar_id} has no files on disk (deleted?)")
    return job
