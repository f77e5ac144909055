"""The job queue and worker: huey (SQLite or Redis) carries job ids, ``JobStore`` holds the records,
``JobRunner`` runs each job in its own process, where ``JobRun`` runs its stages in ``eva_engine``;
``Storage`` keeps avatars, animations and work folders (``jobs.backends``: SQLite and a disk on one
host, or Redis and an S3 bucket across several), ``jobs.sweep`` what crashes leave behind.

    from jobs import JobQueue, JobsConfig
    queue = JobQueue(JobsConfig.from_env())
    job = queue.store.create(JobOptions().model_dump(), filename="clip.mp4")
    queue.enqueue(job.id)           # a worker (``eva worker``) runs it
"""

from jobs.backends import open_storage, open_store
from jobs.config import JobsConfig
from jobs.kinds import KIND_MODULES, job_kind, job_kinds
from jobs.media import VideoInfo, VideoRejected, probe_in_subprocess, probe_video
from jobs.options import JobOptions
from jobs.pipeline import JobCancelled, JobKind, JobRun
from jobs.queue import JobQueue, QueueUnavailable, Recovery, make_huey
from jobs.runner import Crashed, JobRunner
from jobs.storage import InvalidIdError, Storage, StorageUnavailable
from jobs.store import (
    STATES,
    TERMINAL,
    JobLost,
    JobRecord,
    JobStore,
    JobStoreError,
    SqliteJobStore,
    is_valid_id,
    new_id,
)
from jobs.sweep import Sweep, sweep
from jobs.worker import run_worker

__all__ = [
    "KIND_MODULES",
    "STATES",
    "TERMINAL",
    "Crashed",
    "InvalidIdError",
    "JobCancelled",
    "JobKind",
    "JobLost",
    "JobOptions",
    "JobQueue",
    "JobRecord",
    "JobRun",
    "JobRunner",
    "JobStore",
    "JobStoreError",
    "SqliteJobStore",
    "JobsConfig",
    "QueueUnavailable",
    "Recovery",
    "Storage",
    "StorageUnavailable",
    "Sweep",
    "VideoInfo",
    "VideoRejected",
    "is_valid_id",
    "job_kind",
    "job_kinds",
    "make_huey",
    "new_id",
    "open_storage",
    "open_store",
    "probe_in_subprocess",
    "probe_video",
    "run_worker",
    "sweep",
]
