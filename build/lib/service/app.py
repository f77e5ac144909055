"""``create_app(settings)``: the FastAPI application (no module-level state; one app per call).

Requests pass, before routing: the ``Host`` check (``TrustedHostMiddleware``, against DNS
rebinding), then ``RequestGuard`` (API key, cross-site writes, concurrency, body limits; see
``service.guard``). Errors answer with a reason and no internals (those are logged): 4xx for the
client's, 503 with ``Retry-After`` when busy, 507 when the disk is full.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.security import APIKeyHeader
from fastapi.staticfiles import StaticFiles
from redis.exceptions import RedisError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.trustedhost import TrustedHostMiddleware

import eva_engine
from eva_engine.avatar import AvatarFileError
from eva_engine.body import InvalidPoseError
from jobs.disk import is_disk_full
from jobs.media import VideoRejected
from jobs.queue import JobQueue, QueueUnavailable
from jobs.storage import InvalidIdError, StorageUnavailable
from jobs.store import JobStoreError
from service.accounts import caller_keys
from service.deps import ServiceContext
from service.guard import RETRY_AFTER_S, BodyRule, GuardConfig, RequestGuard
from service.rendering import AvatarCache, RenderBusy, RenderGate, RenderInputError
from service.routers import animations, avatars, docs, health, jobs, page
from service.security_headers import SecurityHeaders
from service.settings import ServiceSettings
from service.uploads import UploadTooLarge

logger = logging.getLogger("eva.service")

DESCRIPTION = """Learn a drivable 3D Gaussian avatar (body, fingers, face) from a video of one person
(EVA, NeurIPS 2024), then render it in any pose, expression and view.

1. `POST /avatars` with a video -> `{avatar_id, job_id}`;
2. poll `GET /jobs/{job_id}` until `state` is `succeeded`;
3. `POST /avatars/{avatar_id}/render` with a pose -> an image;
4. `POST /avatars/{avatar_id}/animations` with a driving video -> an mp4 of the avatar performing it.

A web page at `/` does all of this in a browser.

When the service has a key, every call but `/healthz` and the page (these docs included) needs the
header `X-API-Key`. Busy answers are 503 with `Retry-After`.
"""
PUBLIC_PATHS = frozenset({"/healthz"})
# The web page and its files hold no secret: served without the key (the page asks for it).
OPEN_PATHS, OPEN_PREFIXES = frozenset({"/"}), ("/static/",)
FORM_OVERHEAD = 64 * 1024  # multipart boundaries and the option fields around the video
# Uploads: a video for an avatar (POST /avatars), a driving video or JSON poses for an animation
# (POST /avatars/{id}/animations); one rule, so they share the cap on uploads at once.
UPLOAD_PATHS = r"/avatars(/[^/]+/animations)?/?"


def body_rules(settings: ServiceSettings) -> tuple[BodyRule, ...]:
    """The routes whose body may exceed ``max_json_kb`` (every other body is capped at it)."""
    upload = BodyRule("POST", UPLOAD_PATHS, settings.max_upload_bytes + FORM_OVERHEAD, settings.max_uploads)
    return (upload,)


def _validation_errors(exc: RequestValidationError) -> list[dict]:
    # FastAPI's default echoes the input, which may hold NaN (not JSON) or be huge: keep loc, msg, type.
    return [
        {
            "loc": [str(x)[:80] for x in e.get("loc", ())][:8],
            "msg": str(e.get("msg", ""))[:300],
            "type": str(e.get("type", "")),
        }
        for e in exc.errors()[:20]
    ]


def _preload(ctx: ServiceContext) -> None:
    for name in ctx.settings.preload_body_models:
        try:
            ctx.avatars.body(name)
        except Exception:  # a missing optional model (SMPL-X files) must not stop the service
            logger.warning("could not preload body model %r", name, exc_info=True)


def _reply(status: int, detail: str, retry: bool = False) -> JSONResponse:
    headers = {"Retry-After": str(RETRY_AFTER_S)} if retry else None
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _validation_errors(exc)}, status_code=422)

    def reason(status: int):
        async def handler(request: Request, exc: Exception) -> JSONResponse:
            return _reply(status, str(exc)[:2000])

        return handler

    for error, status in (
        (InvalidPoseError, 422),
        (RenderInputError, 422),
        (VideoRejected, 422),
        (InvalidIdError, 404),
        (UploadTooLarge, 413),
    ):
        app.add_exception_handler(error, reason(status))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if is_disk_full(exc.__cause__):  # FastAPI words a failed spool of the upload as a 400
            return _reply(507, "the server's disk is full; retry later")
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(RenderBusy)
    async def _busy(request: Request, exc: RenderBusy) -> JSONResponse:
        return _reply(503, f"the renderer is busy ({exc}); retry shortly", retry=True)

    @app.exception_handler(QueueUnavailable)
    async def _queue_down(request: Request, exc: QueueUnavailable) -> JSONResponse:
        logger.error("job queue unavailable", exc_info=exc)
        return _reply(503, "the job queue is unavailable; retry later", retry=True)

    @app.exception_handler(StorageUnavailable)
    async def _storage_down(request: Request, exc: StorageUnavailable) -> JSONResponse:
        logger.error("storage unavailable", exc_info=exc)
        return _reply(503, "the avatar storage is unavailable; retry later", retry=True)

    @app.exception_handler(RedisError)
    async def _records_down(request: Request, exc: RedisError) -> JSONResponse:
        logger.error("job records (Redis) unavailable", exc_info=exc)
        return _reply(503, "the job records are unavailable; retry later", retry=True)

    @app.exception_handler(sqlite3.OperationalError)
    async def _store_busy(request: Request, exc: sqlite3.OperationalError) -> JSONResponse:
        logger.error("job store error", exc_info=exc)
        if is_disk_full(exc):
            return _reply(507, "the server's disk is full; retry later")
        return _reply(503, "the job records are busy; retry shortly", retry=True)

    @app.exception_handler(OSError)
    async def _os_error(request: Request, exc: OSError) -> JSONResponse:
        if is_disk_full(exc):
            logger.error("disk full", exc_info=exc)
            return _reply(507, "the server's disk is full; retry later")
        logger.error("I/O error in %s %s", request.method, request.url.path, exc_info=exc)
        return _reply(500, "internal error (details in the server's log)")

    @app.exception_handler(AvatarFileError)
    async def _broken_avatar(request: Request, exc: AvatarFileError) -> JSONResponse:
        logger.error("avatar files unreadable", exc_info=exc)
        return _reply(409, "the avatar's files are incomplete or unreadable")

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        logger.error("unhandled error in %s %s", request.method, request.url.path, exc_info=exc)
        return _reply(500, "internal error (details in the server's log)")


def create_app(settings: ServiceSettings | None = None, queue: JobQueue | None = None) -> FastAPI:
    """The service. ``queue``: an existing ``JobQueue`` (default: built from ``settings.jobs``)."""
    settings = settings or ServiceSettings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # Jobs whose worker died while no worker was alive to notice.
        ctx: ServiceContext = app.state.context
        ctx.queue.recover()
        if ctx.settings.preload_body_models:
            threading.Thread(target=_preload, args=(ctx,), daemon=True, name="preload").start()
        yield

    app = FastAPI(
        title="EVA avatar service",
        version=eva_engine.__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # routers.docs serves it with its own files, not a CDN's
        redoc_url=None,
    )
    try:
        job_queue = queue or JobQueue(settings.jobs)
    except (JobStoreError, StorageUnavailable) as err:
        raise ValueError(str(err)) from err
    app.state.context = ServiceContext(
        settings=settings,
        queue=job_queue,
        avatars=AvatarCache(settings.avatar_cache),
        renders=RenderGate(settings.max_renders, settings.render_queue, settings.render_wait_s),
    )
    guard = GuardConfig(
        keys=caller_keys(settings.api_key, settings.accounts),
        public_paths=PUBLIC_PATHS,
        trusted_hosts=tuple(settings.trusted_hosts),
        rules=body_rules(settings),
        default_max_bytes=settings.max_json_bytes,
        max_requests=settings.max_requests,
        body_timeout_s=settings.body_timeout_s,
        body_min_rate=settings.body_min_kb_s * 1024,
        body_grace_s=settings.body_grace_s,
        open_paths=OPEN_PATHS,
        open_prefixes=OPEN_PREFIXES,
    )
    app.add_middleware(RequestGuard, config=guard)
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=settings.trusted_hosts)
    app.add_middleware(SecurityHeaders)  # outermost: on every answer, refusals included
    _install_error_handlers(app)

    # Declares the header in the OpenAPI document; the check itself is the guard's.
    documented_key = [
        Depends(APIKeyHeader(name="X-API-Key", auto_error=False, description="When the service has a key."))
    ]
    app.include_router(health.router)
    app.include_router(avatars.router, dependencies=documented_key)
    app.include_router(animations.router, dependencies=documented_key)
    app.include_router(jobs.router, dependencies=documented_key)
    app.include_router(page.router)
    app.include_router(docs.router)
    app.mount("/static", StaticFiles(directory=page.STATIC_DIR), name="static")
    return app
