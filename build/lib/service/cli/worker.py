"""``eva worker``: run avatar jobs from the queue (a huey consumer)."""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from service.cli.app import app


@app.command()
def worker(
    data_dir: Path | None = typer.Option(
        None, help="Avatars and job files (default EVA_SERVICE_DIR, else the engine's data dir)."
    ),
    queue_url: str | None = typer.Option(
        None, help="redis://host:port/db for Redis (default: SQLite in the data dir, or EVA_QUEUE_URL)."
    ),
    workers: int = typer.Option(1, min=1, help="Jobs run at once in this process."),
    threads: int | None = typer.Option(None, min=1, help="Torch CPU threads per job."),
    stale_after: float | None = typer.Option(
        None, min=1.0, help="Seconds without a heartbeat after which a running job is taken back."
    ),
    memory_mb: int | None = typer.Option(
        None, min=0, help="Memory limit per job process, MB (default 8192 or EVA_JOB_MEMORY_MB; 0: none)."
    ),
    health_file: Path | None = typer.Option(
        None, envvar="EVA_WORKER_HEALTH_FILE", help="Touch this file every 10 s while alive (containers)."
    ),
) -> None:
    """Consume jobs until interrupted (Ctrl-C finishes the running job first). Each job runs in its
    own process under a memory limit. Jobs a killed worker left running are retried from their
    last completed stage when a worker starts."""
    from jobs.config import JobsConfig
    from jobs.worker import run_worker

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        config = JobsConfig.from_env(
            data_dir=data_dir,
            queue_url=queue_url,
            threads=threads,
            stale_after_s=stale_after,
            job_memory_mb=memory_mb,  # 0: no limit
        )
    except ValueError as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from err
    run_worker(config, workers=workers, health_file=health_file)
