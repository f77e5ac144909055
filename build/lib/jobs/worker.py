"""``run_worker``: a huey consumer that runs avatar jobs (``eva worker``), each in its own
process (``jobs.runner``).

It first takes back jobs its dead predecessors left ``running`` and sweeps leftovers (see
``JobQueue.recover``, ``jobs.sweep``), then consumes; the periodic tasks catch workers that die
later, on any machine. With ``health_file``, a thread touches that file every
``HEALTH_EVERY_S`` seconds: a container's health check reads its age (``service.healthcheck``).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from jobs.config import JobsConfig
from jobs.queue import JobQueue
from jobs.sweep import sweep

logger = logging.getLogger("eva.jobs")

HEALTH_EVERY_S = 10.0


def _touch_forever(path: Path, stop: threading.Event) -> None:
    while True:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        except OSError:
            logger.warning("cannot touch the health file %s", path, exc_info=True)
        if stop.wait(HEALTH_EVERY_S):
            return


def run_worker(
    config: JobsConfig, workers: int = 1, poll_s: float = 1.0, health_file: Path | None = None
) -> None:
    """Consume jobs until SIGINT (finish running jobs) or SIGTERM (stop now; recovery retries
    them). Must run in the main thread (huey installs signal handlers)."""
    queue = JobQueue(config)
    me = queue.runner.worker
    recovered = queue.recover(this_worker=me)
    swept = sweep(config, queue.store, queue.storage)
    logger.info(
        "worker %s: queue %s, data %s; recovered %s; swept %d folder(s), %d record(s)",
        me,
        config.queue_url or config.sqlite_queue_path,
        config.data_dir,
        recovered,
        len(swept.folders),
        len(swept.records),
    )
    stop = threading.Event()
    if health_file is not None:
        threading.Thread(target=_touch_forever, args=(health_file, stop), daemon=True, name="health").start()
    consumer = queue.huey.create_consumer(
        workers=workers,
        worker_type="thread",
        initial_delay=0.1,
        backoff=1.15,
        max_delay=poll_s,
        periodic=True,
        check_worker_health=True,
    )
    try:
        consumer.run()
    finally:
        stop.set()
        if health_file is not None:
            health_file.unlink(missing_ok=True)
