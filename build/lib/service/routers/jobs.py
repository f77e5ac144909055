from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import JSONResponse

from jobs.store import JobRecord
from service.deps import ServiceContext, context, job_record
from service.routers.responses import error
from service.schemas import JobInfo

router = APIRouter(prefix="/jobs", tags=["jobs"])
NOT_FOUND = error(404, "Unknown or malformed job id")


@router.get("/{job_id}", response_model=JobInfo, responses=NOT_FOUND, summary="A job's state and progress")
def get_job(job: JobRecord = Depends(job_record)) -> JobInfo:
    return JobInfo.of(job)


@router.delete(
    "/{job_id}",
    response_model=JobInfo,
    summary="Cancel a job",
    description="A queued job is cancelled at once (200); a running one stops at its next progress "
    "report (202, `cancel_requested` true). A finished job cannot be cancelled (409).",
    responses={**NOT_FOUND, 202: {"model": JobInfo}, **error(409, "The job has already finished")},
)
def cancel_job(job: JobRecord = Depends(job_record), ctx: ServiceContext = Depends(context)):
    if job.finished:
        raise HTTPException(409, f"job {job.id} already {job.state}; nothing to cancel")
    job = ctx.queue.cancel(job)
    info = JobInfo.of(job)
    return info if job.finished else JSONResponse(info.model_dump(mode="json"), status_code=202)
