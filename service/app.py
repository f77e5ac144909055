"""``create_app(settings)``: the FastAPI application (no module-level state; one app per call)."""

from __future__ import annotations

import logging
import threading
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

import eva_engine
from eva_engine.avatar.render_spec import RenderInputError
from eva_engine.body import InvalidPoseError
from eva_engine.data import VideoError
from jobs.queue import JobQueue
from jobs.storage import InvalidIdError
from service.deps import ServiceContext, require_api_key
from service.rendering import AvatarCache
from service.routers import animations, avatars, health, jobs, page
from service.settings import ServiceSettings
from service.uploads import UploadLimit, UploadTooLarge

DESCRIPTION = """Learn a drivable 3D Gaussian avatar (body, fingers, face) from a video of one person
(EVA, NeurIPS 2024), then render it in any pose, expression and view.

1. `POST /avatars` with a video -> `{avatar_id, job_id}`;
2. poll `GET /jobs/{job_id}` until `state` is `succeeded`;
3. `POST /avatars/{avatar_id}/render` with a pose -> an image;
4. `POST /avatars/{avatar_id}/animations` with a driving video -> an mp4 of the avatar performing it.

A web page at `/` does all of this in a browser.
"""


def _validation_errors(exc: RequestValidationError) -> list[dict]:
    # FastAPI's default echoes the input, which may hold NaN (not JSON): keep loc, msg, type.
    return [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
            for e in exc.errors()]  # fmt: skip


def _preload(ctx: ServiceContext) -> None:
    for name in ctx.settings.preload_body_models:
        try:
            ctx.avatars.body(name)
        except Exception:  # a missing optional model (SMPL-X files) must not stop the service
            logging.getLogger("eva.service").warning("could not preload body model %r", name, exc_info=True)


def create_app(settings: ServiceSettings | None = None, queue: JobQueue | None = None) -> FastAPI:
    """The service. ``queue``: an existing ``JobQueue`` (default: built from ``settings.jobs``)."""
    settings = settings or ServiceSettings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # Jobs whose worker died while no worker was alive to notice (stale heartbeats only).
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
    )
    app.state.context = ServiceContext(
        settings=settings,
        queue=queue or JobQueue(settings.jobs),
        avatars=AvatarCache(settings.avatar_cache),
    )
    # Uploads: a video for an avatar, a driving video (or poses) for an animation.
    app.add_middleware(UploadLimit, path=r"/avatars(/[^/]+/animations)?", max_bytes=settings.max_upload_bytes)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _validation_errors(exc)}, status_code=422)

    def reason(status: int):
        async def handler(request: Request, exc: Exception) -> JSONResponse:
            return JSONResponse({"detail": str(exc)}, status_code=status)

        return handler

    for error, status in ((InvalidPoseError, 422), (RenderInputError, 422), (VideoError, 422),
                          (InvalidIdError, 404), (UploadTooLarge, 413)):  # fmt: skip
        app.add_exception_handler(error, reason(status))

    secured = [Depends(require_api_key)]
    app.include_router(health.router)
    app.include_router(avatars.router, dependencies=secured)
    app.include_router(animations.router, dependencies=secured)
    app.include_router(jobs.router, dependencies=secured)
    app.include_router(page.router)
    app.mount("/static", StaticFiles(directory=page.STATIC_DIR), name="static")
    return app
