"""``JobQueue``: the huey queue (SQLite by default, Redis when the queue URL names it), its tasks,
and the recovery of jobs whose worker died.

The API and the workers each build one from the same ``JobsConfig``; task names are fixed, so a
message enqueued by one process runs in another. huey drops a message once a worker takes it, so
the job record (``jobs.store``) is the truth: a job left ``running`` by a dead worker is sent back
to the queue (resuming after its last completed stage) or, after ``max_attempts``, failed.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from dataclasses import dataclass

from huey import RedisHuey, SqliteHuey, crontab

from jobs.config import JobsConfig
from jobs.pipeline import Pipeline
from jobs.storage import Storage
from jobs.store import JobRecord, JobStore

logger = logging.getLogger("eva.jobs")

RUN_TASK, RECOVER_TASK = "eva.run_job", "eva.recover_jobs"


def make_huey(config: JobsConfig, immediate: bool = False):
    if config.uses_redis:
        return RedisHuey(config.queue_name, url=config.queue_url, immediate=immediate)
    path = config.sqlite_queue_path
    path.parent.mkdir(parents=True, exist_ok=True)
    return SqliteHuey(config.queue_name, filename=str(path), immediate=immediate, immediate_use_memory=False)


@dataclass
class Recovery:
    """What one recovery pass did: job ids sent back to the queue and job ids failed."""

    requeued: list[str]
    failed: list[str]


class JobQueue:
    """The queue, its two tasks (run a job; every minute, recover orphaned jobs) and the store."""

    def __init__(self, config: JobsConfig, immediate: bool = False) -> None:
        self.config = config
        self.store = JobStore(config.db_path)
        self.storage = Storage(config)
        self.huey = make_huey(config, immediate)
        self._pipeline: Pipeline | None = None
        self._run_task = self.huey.task(name=RUN_TASK)(self._run)
        self.huey.periodic_task(crontab(minute="*"), name=RECOVER_TASK)(self._recover_periodic)

    @property
    def pipeline(self) -> Pipeline:
        """Created on first use, in the process that runs jobs (a worker)."""
        if self._pipeline is None:
            self._pipeline = Pipeline(self.config, self.store, self.storage)
        return self._pipeline

    # -- producer side (API) ---------------------------------------------------------------------
    def enqueue(self, job_id: str) -> None:
        self._run_task(job_id)

    def cancel(self, job: JobRecord) -> JobRecord:
        """Cancel a queued job now; ask a running one to stop (its worker ends it as cancelled)."""
        if job.state == "queued" and self.store.finish(
            job.id, "cancelled", message="cancelled before it started", from_states=("queued",)
        ):
            self.storage.remove_work(job.id)
        elif job.state in ("queued", "running"):  # running, or claimed since we read it
            self.store.update(job.id, where_state=("running",), cancel_requested=1, message="cancelling")
        return self.store.get(job.id) or job

    # -- consumer side (worker) ------------------------------------------------------------------
    def _run(self, job_id: str) -> str | None:
        return self.pipeline.run(job_id)

    def _recover_periodic(self) -> None:
        self.recover()

    def run_pending(self) -> int:
        """Run every queued message in this process, in order (tests, ``eva worker --drain``)."""
        count = 0
        while (task := self.huey.dequeue()) is not None:
            self.huey.execute(task)
            count += 1
        return count

    def recover(self, this_worker: str | None = None) -> Recovery:
        """Send running jobs whose worker is gone back to the queue, or fail them after
        ``max_attempts``. A worker is gone when its heartbeat is older than ``stale_after_s``, or
        at once when it ran on this host and its process no longer exists (or is us, restarted)."""
        requeued, failed = [], []
        now = time.time()
        for job in self.store.list(states=("running",), with_deleted=True):
            if not self._worker_gone(job, now, this_worker):
                continue
            stage = job.stage or "preprocess"
            if job.cancel_requested:
                if self.store.finish(job.id, "cancelled", message="cancelled (its worker stopped)"):
                    self.storage.remove_work(job.id)
                continue
            if job.attempts >= self.config.max_attempts:
                reason = (f"the worker stopped during stage {stage!r} {job.attempts} time(s); "
                          f"giving up after {self.config.max_attempts} attempts")  # fmt: skip
                if self.store.finish(job.id, "failed", error=reason):
                    self.storage.remove_work(job.id)
                    failed.append(job.id)
                continue
            resume = _next_stage(job.completed_stage, job.kind)
            changed = self.store.update(
                job.id, where_state=("running",), state="queued", worker=None, stage=resume, eta_s=None,
                message=f"worker stopped during stage {stage!r}; retrying from stage {resume!r}",
            )  # fmt: skip
            if changed:
                self.enqueue(job.id)
                requeued.append(job.id)
        if requeued or failed:
            logger.warning("recovered jobs: requeued %s, failed %s", requeued, failed)
        return Recovery(requeued, failed)

    def _worker_gone(self, job: JobRecord, now: float, this_worker: str | None) -> bool:
        beat = job.heartbeat_at or job.updated_at
        if now - beat > self.config.stale_after_s:
            return True
        host, _, rest = (job.worker or "").partition(":")
        pid, _, _token = rest.partition(":")
        if host != socket.gethostname() or not pid.isdigit():
            return False
        if job.worker == this_worker:
            return False
        if int(pid) == os.getpid():  # our pid, another token: a previous life of this process
            return this_worker is not None
        return not _pid_alive(int(pid))


def _next_stage(completed: str | None, kind: str = "avatar") -> str:
    from jobs.store import STAGES_OF

    stages = STAGES_OF[kind]
    if completed is None:
        return stages[0]
    index = stages.index(completed)
    return stages[min(index + 1, len(stages) - 1)]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie (killed, not yet reaped by its parent) counts as gone.
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True
