"""``JobQueue``: the huey queue (SQLite by default, Redis when the queue URL names it), its tasks,
and the recovery of jobs whose worker died.

The API and the workers each build one from the same ``JobsConfig``; task names are fixed, so a
message enqueued by one process runs in another. huey drops a message once a worker takes it, so
the job record (``jobs.store``) is the truth: a job left ``running`` by a dead worker is sent back
to the queue (resuming after its last completed stage) or, after ``max_attempts``, failed, and a
``queued`` job whose message never made it (the API died before enqueueing, Redis lost it) is
sent again.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from huey import RedisHuey, SqliteHuey, crontab

from jobs.backends import open_storage, open_store
from jobs.config import JobsConfig
from jobs.kinds import job_kind
from jobs.runner import Crashed, JobRunner, WorkerId
from jobs.store import JobRecord

logger = logging.getLogger("eva.jobs")

RUN_TASK, RECOVER_TASK, SWEEP_TASK = "eva.run_job", "eva.recover_jobs", "eva.sweep"
_ENQUEUE_RETRIES = 3


class QueueUnavailable(RuntimeError):
    """The queue backend (Redis, or huey's SQLite file) could not take a message."""


def make_huey(config: JobsConfig, immediate: bool = False):
    # results=False: the job record is the result; huey would keep every task's return value.
    if config.uses_redis:
        return RedisHuey(config.queue_name, url=config.queue_url, immediate=immediate, results=False)
    path = config.sqlite_queue_path
    path.parent.mkdir(parents=True, exist_ok=True)
    return SqliteHuey(
        config.queue_name, filename=str(path), immediate=immediate, immediate_use_memory=False, results=False
    )


def _transient_queue_errors() -> tuple[type[BaseException], ...]:
    import sqlite3

    from redis.exceptions import ConnectionError as RedisConnectionError
    from redis.exceptions import TimeoutError as RedisTimeoutError

    return (RedisConnectionError, RedisTimeoutError, sqlite3.OperationalError, OSError)


@dataclass
class Recovery:
    """What one recovery pass did: running jobs sent back to the queue, running jobs failed
    (attempts used up) or cancelled, and queued jobs whose message was lost, sent again."""

    requeued: list[str]
    failed: list[str]
    resent: list[str] = field(default_factory=list)
    cancelled: list[str] = field(default_factory=list)


class JobQueue:
    """The queue, its tasks (run a job; every minute, recover orphaned jobs; every ten minutes,
    sweep old files and records) and the store."""

    def __init__(self, config: JobsConfig, immediate: bool = False) -> None:
        self.config = config
        self.store = open_store(config)
        self.storage = open_storage(config)
        self.huey = make_huey(config, immediate)
        self._runner: JobRunner | None = None
        self._run_task = self.huey.task(name=RUN_TASK)(self._run)
        self.huey.periodic_task(crontab(minute="*"), name=RECOVER_TASK)(self._recover_periodic)
        self.huey.periodic_task(crontab(minute="*/10"), name=SWEEP_TASK)(self._sweep_periodic)

    @property
    def runner(self) -> JobRunner:
        """Created on first use, in the process that runs jobs (a worker)."""
        if self._runner is None:
            self._runner = JobRunner(self.config, self.store, self.storage)
        return self._runner

    # -- producer side (API) ---------------------------------------------------------------------
    def enqueue(self, job_id: str) -> None:
        """Send the job's message, retrying transient backend errors; raises ``QueueUnavailable``."""
        errors = _transient_queue_errors()
        for attempt in range(_ENQUEUE_RETRIES):
            try:
                self._run_task(job_id)
                break
            except errors as err:
                if attempt == _ENQUEUE_RETRIES - 1:
                    raise QueueUnavailable(f"the job queue is unavailable ({type(err).__name__})") from err
                logger.warning("enqueue of job %s failed (%s); retrying", job_id, err)
                time.sleep(0.25 * 2**attempt)
        self.store.update(job_id, where_state=("queued",), enqueued_at=time.time())

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
        try:
            outcome = self.runner.run(job_id)
        except Exception:  # never leave a job running under a worker that is alive but done with it
            logger.exception("job %s: the worker failed while running it", job_id)
            job = self.store.get(job_id)
            if job is None or job.state != "running" or job.worker != self.runner.worker:
                return None
            outcome = Crashed(job, "the worker hit an internal error while running the job")
        if isinstance(outcome, Crashed):
            logger.warning("job %s: %s", job_id, outcome.reason)
            return self._give_back(outcome.job, outcome.reason, owner=self.runner.worker)
        return outcome

    def _recover_periodic(self) -> None:
        self.recover()

    def _sweep_periodic(self) -> None:
        from jobs.sweep import sweep

        sweep(self.config, self.store, self.storage)

    def run_pending(self) -> int:
        """Run every queued message in this process, in order (tests, ``eva worker --drain``)."""
        count = 0
        while (task := self.huey.dequeue()) is not None:
            self.huey.execute(task)
            count += 1
        return count

    def recover(self, this_worker: str | None = None) -> Recovery:
        """Running jobs whose worker is gone go back to the queue (or fail after
        ``max_attempts``); queued jobs whose message is not in the queue after
        ``requeue_after_s`` are sent again. Every change is a compare-and-set on the record as
        read here (state, worker, heartbeat), so workers recovering at the same moment, or a
        worker that comes back to life, cannot both win."""
        result = Recovery([], [])
        now = time.time()
        for job in self.store.list(states=("running",), with_deleted=True):
            if not self._worker_gone(job, now, this_worker):
                continue
            outcome = self._give_back(job, f"its worker ({job.worker}) stopped", worker_lost=True, expect=job)
            {"requeued": result.requeued, "failed": result.failed, "cancelled": result.cancelled}.get(
                outcome or "", []
            ).append(job.id)
        stale = [
            j
            for j in self.store.list(states=("queued",), with_deleted=True)
            if now - (j.enqueued_at or j.created_at) > self.config.requeue_after_s
        ]
        if stale:
            waiting = self._pending_job_ids()
            for job in stale:
                if job.id not in waiting and self.store.update(job.id, expect=job, enqueued_at=now):
                    self.enqueue(job.id)
                    result.resent.append(job.id)
        if result.requeued or result.failed or result.resent or result.cancelled:
            logger.warning(
                "recovered jobs: requeued %s, failed %s, resent %s, cancelled %s",
                result.requeued,
                result.failed,
                result.resent,
                result.cancelled,
            )
        return result

    def _pending_job_ids(self) -> set[str]:
        return {t.args[0] for t in self.huey.pending() if t.name == RUN_TASK and t.args}

    def _give_back(self, job: JobRecord, why: str, worker_lost: bool = False, **condition) -> str | None:
        """A running job whose attempt ended without ending it: back to the queue (resuming after
        its last completed stage), or cancelled / failed with the reason. ``worker_lost``: the
        worker under it died, which counts against ``max_worker_losses``, not ``max_attempts``
        (a job killed with its worker twice kept failing, upload lost, in the soak run).
        ``condition``: ``owner=`` or ``expect=`` as in ``JobStore.update``. Returns what happened,
        or None if the job had changed meanwhile."""
        kind = job_kind(job.kind)
        stage = job.stage or kind.stages[0]
        losses = job.worker_losses + int(worker_lost)
        crashes = job.attempts - losses
        if job.cancel_requested:
            state, fields = "cancelled", {"message": f"cancelled ({why})"}
        elif worker_lost and losses >= self.config.max_worker_losses:
            state = "failed"
            fields = {
                "error": f"{why} during stage {stage!r}; giving up after {losses} workers stopped "
                "under this job"
            }
        elif not worker_lost and crashes >= self.config.max_attempts:
            state = "failed"
            fields = {
                "error": f"{why} during stage {stage!r}, {crashes} time(s); giving up after "
                f"{self.config.max_attempts} attempts"
            }
        else:
            resume = kind.next_stage(job.completed_stage)
            changed = self.store.update(
                job.id,
                **condition,
                state="queued",
                worker=None,
                worker_losses=losses,
                stage=resume,
                eta_s=None,
                message=f"{why} during stage {stage!r}; retrying from stage {resume!r}",
            )
            if not changed:
                return None
            self.enqueue(job.id)
            return "requeued"
        if not self.store.finish(job.id, state, from_states=("running",), **condition, **fields):
            return None
        self.storage.remove_work(job.id)
        return state

    def _worker_gone(self, job: JobRecord, now: float, this_worker: str | None) -> bool:
        """Same host (and pid namespace): gone when its process is, whatever the heartbeat says
        (fitting can be silent for minutes). Elsewhere: when its heartbeat is stale."""
        if job.worker == this_worker:
            return False
        worker = WorkerId.parse(job.worker)
        if worker is not None and worker.local():
            return not worker.alive()
        beat = job.heartbeat_at or job.updated_at
        return now - beat > self.config.stale_after_s
