"""``run_worker``: a huey consumer that runs avatar jobs (``eva worker``).

It first takes back jobs its dead predecessors left ``running`` (see ``JobQueue.recover``), then
consumes; the periodic recovery task catches workers that die later, on any machine.
"""

from __future__ import annotations

import logging

from jobs.config import JobsConfig
from jobs.queue import JobQueue

logger = logging.getLogger("eva.jobs")


def run_worker(config: JobsConfig, workers: int = 1, poll_s: float = 1.0) -> None:
    """Consume jobs until SIGINT (finish running jobs) or SIGTERM (stop now; recovery retries
    them). Must run in the main thread (huey installs signal handlers)."""
    queue = JobQueue(config)
    recovered = queue.recover(this_worker=queue.pipeline.worker)
    logger.info("worker %s: queue %s, data %s; recovered %s", queue.pipeline.worker,
                config.queue_url or config.sqlite_queue_path, config.data_dir, recovered)  # fmt: skip
    consumer = queue.huey.create_consumer(
        workers=workers, worker_type="thread", initial_delay=0.1, backoff=1.15, max_delay=poll_s,
        periodic=True, check_worker_health=True,
    )  # fmt: skip
    consumer.run()
