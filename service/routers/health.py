from __future__ import annotations

from fastapi import APIRouter, Depends

import eva_engine
from jobs.store import STATES
from service.deps import ServiceContext, context
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness, queue kind and job counts")
def healthz(ctx: ServiceContext = Depends(context)) -> Health:
    counts = dict.fromkeys(STATES, 0)
    for job in ctx.queue.store.list(with_deleted=True):
        counts[job.state] += 1
    return Health(version=eva_engine.__version__, queue="redis" if ctx.queue.config.uses_redis else "sqlite",
                  jobs=counts)  # fmt: skip
