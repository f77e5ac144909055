"""Request dependencies: the app's context and ids resolved to records (404s). The API key is
checked before routing, by ``service.guard``."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

from fastapi import Depends, HTTPException, Request
from fastapi.concurrency import run_in_threadpool

from jobs.queue import JobQueue
from jobs.store import JobRecord, is_valid_id
from service.accounts import LOCAL, Caller
from service.guard import RETRY_AFTER_S
from service.rendering import AvatarCache, RenderGate
from service.settings import ServiceSettings


@dataclass
class JobCounts:
    """Jobs per state for ``/healthz``, which must answer at once even while the store is locked:
    counts older than ``max_age_s`` are read again from the store (in a thread), and waited for
    at most ``wait_s``; a store that takes longer leaves the last counts read, with their age.
    (Returning the last counts and reading anew only behind them showed a rarely polled
    ``/healthz`` counts as old as its previous poll.)"""

    max_age_s: float = 1.0
    wait_s: float = 0.25
    _value: dict[str, int] | None = None
    _at: float = field(default=float("-inf"))
    _refresh: asyncio.Task | None = None

    async def get(self, queue: JobQueue) -> tuple[dict[str, int], float]:
        """(counts, their age in seconds)."""
        if time.monotonic() - self._at > self.max_age_s:
            if self._refresh is None or self._refresh.done():
                self._refresh = asyncio.create_task(self._read(queue))
            wait = None if self._value is None else self.wait_s  # the very first read: its answer
            try:
                await asyncio.wait_for(asyncio.shield(self._refresh), timeout=wait)
            except TimeoutError:
                pass
            except Exception:  # a store error: health shows the last counts and their age
                if self._value is None:
                    raise
        return self._value, round(time.monotonic() - self._at, 3)

    async def _read(self, queue: JobQueue) -> None:
        self._value, self._at = await run_in_threadpool(queue.store.counts), time.monotonic()


@dataclass
class ServiceContext:
    """Everything a request needs, held by the app (no module-level state)."""

    settings: ServiceSettings
    queue: JobQueue
    avatars: AvatarCache
    renders: RenderGate
    job_counts: JobCounts = field(default_factory=JobCounts)


async def context(request: Request) -> ServiceContext:  # async: no thread hop for a lookup
    return request.app.state.context


async def render_admission(ctx: ServiceContext = Depends(context)) -> None:
    """Refuse a render (503) before its body is validated or its avatar looked up, when the
    render gate could not even let it wait."""
    ctx.renders.admit()


async def caller(request: Request) -> Caller:
    """Who made the request, as ``RequestGuard`` identified them (the local user without
    accounts)."""
    who = request.scope.get("state", {}).get("caller")
    if who is None:
        raise HTTPException(401, "missing or wrong API key (header X-API-Key)")
    return who


def _record(what: str, value: str, find: Callable[[str], JobRecord | None], who: Caller) -> JobRecord:
    """What ``find`` answers for a well-formed id that ``who`` may see; 404 for a malformed or
    unknown one, and for another owner's (the same answer: an id says nothing about its owner)."""
    if not is_valid_id(value):
        raise HTTPException(404, f"no {what} with id {value!r} (ids are 32 lowercase hex characters)")
    job = find(value)
    if job is None or not who.sees(job.account):
        raise HTTPException(404, f"no {what} with id {value!r}")
    return job


def job_record(
    job_id: str, ctx: ServiceContext = Depends(context), who: Caller = Depends(caller)
) -> JobRecord:
    return _record("job", job_id, ctx.queue.store.get, who)


def avatar_record(
    avatar_id: str, ctx: ServiceContext = Depends(context), who: Caller = Depends(caller)
) -> JobRecord:
    """The job record behind an avatar (one job makes one avatar)."""
    return _record("avatar", avatar_id, ctx.queue.store.by_output, who)


def animation_record(
    animation_id: str, ctx: ServiceContext = Depends(context), who: Caller = Depends(caller)
) -> JobRecord:
    """The job record behind an animation (its ``output_id`` is the animation's id)."""
    return _record("animation", animation_id, partial(ctx.queue.store.by_output, kind="animation"), who)


def ready_avatar(
    job: JobRecord = Depends(avatar_record), ctx: ServiceContext = Depends(context)
) -> JobRecord:
    """409 unless the avatar is finished and on disk."""
    return check_ready(job, ctx)


def check_ready(job: JobRecord, ctx: ServiceContext) -> JobRecord:
    """``ready_avatar`` called from a route, after FastAPI has validated its body (a dependency's
    409 would come before the body's 422)."""
    if job.state != "succeeded":
        reason = {
            "queued": "its job is queued",
            "running": f"its job is running (stage {job.stage})",
            "failed": f"its job failed: {job.error}",
            "cancelled": "its job was cancelled",
        }[job.state]
        raise HTTPException(409, f"avatar {job.output_id} is not ready: {reason}")
    if not ctx.queue.storage.avatar_exists(job.output_id):
        raise HTTPException(409, f"avatar {job.output_id} has no files on disk (deleted?)")
    return job


def check_job_quota(ctx: ServiceContext, who: Caller = LOCAL) -> None:
    """503 with ``Retry-After`` when ``max_queued_jobs`` jobs (avatars and animations) already wait
    for a worker: ``who``'s own jobs when the service has accounts (one owner cannot lock the
    others out), all jobs otherwise. Blocking (reads the store): call it from a thread."""
    queued = ctx.queue.store.queued(who.account)
    if queued >= ctx.settings.max_queued_jobs:
        whose = "of yours " if who.account is not None else ""
        raise HTTPException(
            503,
            f"{queued} jobs {whose}are waiting for a worker (the quota); retry later",
            headers={"Retry-After": str(30 * RETRY_AFTER_S)},
        )
