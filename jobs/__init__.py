"""The job queue and worker: huey (SQLite or Redis) carries job ids, SQLite holds the job records,
``Pipeline`` runs a job's stages in ``eva_engine``, ``Storage`` keeps avatars and work folders.

    from jobs import JobQueue, JobsConfig
    queue = JobQueue(JobsConfig.from_env())
    job = queue.store.create(JobOptions().model_dump(), filename="clip.mp4")
    queue.enqueue(job.id)           # a worker (``eva worker``) runs it
"""

from jobs.config import JobsConfig
from jobs.options import JobOptions
from jobs.pipeline import STAGE_SPANS, JobCancelled, Pipeline
from jobs.queue import JobQueue, Recovery, make_huey
from jobs.storage import InvalidIdError, Storage
from jobs.store import STAGES, STATES, TERMINAL, JobRecord, JobStore, is_valid_id, new_id
from jobs.worker import run_worker

__all__ = [
    "STAGES",
    "STAGE_SPANS",
    "STATES",
    "TERMINAL",
    "InvalidIdError",
    "JobCancelled",
    "JobOptions",
    "JobQueue",
    "JobRecord",
    "JobStore",
    "JobsConfig",
    "Pipeline",
    "Recovery",
    "Storage",
    "is_valid_id",
    "make_huey",
    "new_id",
    "run_worker",
]
