from __future__ import annotations

from fastapi import APIRouter, Depends

import eva_engine
from service.deps import ServiceContext, context
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness, queue kind, job counts, renders")
async def healthz(ctx: ServiceContext = Depends(context)) -> Health:
    counts, age = await ctx.job_counts.get(ctx.queue)  # one grouped query a second at most, in a thread
    renders = {"running": ctx.renders.running, "waiting": ctx.renders.queued}
    return Health(
        version=eva_engine.__version__,
        queue="redis" if ctx.queue.config.uses_redis else "sqlite",
        records="sqlite" if ctx.queue.config.records_url is None else "redis",
        storage="disk" if ctx.queue.config.storage_url is None else "s3",
        jobs=counts,
        jobs_age_s=age,
        renders=renders,
    )
