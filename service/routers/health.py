from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.concurrency import run_in_threadpool

import eva_engine
from service.deps import ServiceContext, context
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness, queue kind, job counts, renders")
async def healthz(ctx: ServiceContext = Depends(context)) -> Health:
    counts = await run_in_threadpool(ctx.queue.store.counts)  # one grouped query, off the event loop
    renders = {"running": ctx.renders.running, "waiting": ctx.renders.queued}
    return Health(version=eva_engine.__version__, queue="redis" if ctx.queue.config.uses_redis else "sqlite",
                  jobs=counts, renders=renders)  # fmt: skip
