"""``eva serve``: run the REST service (FastAPI + uvicorn) on 127.0.0.1 by default; any other
address needs an API key."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from service.cli.app import app


@app.command()
def serve(
    host: str | None = typer.Option(None, help="Bind address (default 127.0.0.1, or EVA_HOST)."),
    port: int | None = typer.Option(None, min=1, max=65535, help="Port (default 8000, or EVA_PORT)."),
    data_dir: Path | None = typer.Option(
        None, help="Avatars and job files (default EVA_SERVICE_DIR, else the engine's data dir)."
    ),
    queue_url: str | None = typer.Option(
        None, help="redis://host:port/db for Redis (default: SQLite in the data dir, or EVA_QUEUE_URL)."
    ),
    api_key_file: Path | None = typer.Option(
        None,
        exists=True,
        dir_okay=False,
        help="A file holding the key that the X-API-Key header must carry (or set EVA_API_KEY; "
        "never on the command line, where `ps` shows it); needed to bind a non-loopback address.",
    ),
    api_keys_file: Path | None = typer.Option(
        None,
        exists=True,
        dir_okay=False,
        help="Several keys, each with its owner, who sees only their own avatars (JSON, "
        "docs/deployment.md; or EVA_API_KEYS_FILE); instead of --api-key-file.",
    ),
    max_upload_mb: float | None = typer.Option(None, min=0.001, help="Upload size limit (default 512)."),
    log_level: str = typer.Option("info", help="uvicorn log level."),
) -> None:
    """Serve the API: POST /avatars, GET /jobs/{id}, POST /avatars/{id}/render ... (docs at /docs).
    Run ``eva worker`` beside it (same data dir and queue) to process the jobs."""
    prefer_passive_openmp()
    from jobs.config import JobsConfig
    from service.accounts import read_accounts
    from service.server import serve as run_server
    from service.settings import ServiceSettings

    try:
        api_key = read_key_file(api_key_file) if api_key_file is not None else None
        accounts = read_accounts(api_keys_file) if api_keys_file is not None else None
        jobs = JobsConfig.from_env(data_dir=data_dir, queue_url=queue_url)
        settings = ServiceSettings.from_env(
            jobs, host=host, port=port, api_key=api_key, accounts=accounts, max_upload_mb=max_upload_mb
        )
    except ValueError as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from err
    try:
        run_server(settings, log_level=log_level)
    except ValueError as err:  # e.g. job records on a network file system
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from err


def read_key_file(path: Path) -> str:
    """The key in ``path``: its text without surrounding whitespace (a trailing newline)."""
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"cannot read the API key file {path}: {err}") from err


def prefer_passive_openmp() -> None:
    """Idle OpenMP threads sleep instead of spinning (``OMP_WAIT_POLICY=PASSIVE``) unless the
    environment says otherwise. Between renders the server encodes images and answers requests
    on the same cores; spinning render threads slowed 16 clients to ~0.9x one client's throughput
    (``bench/serving.py latency``). Read once, when torch loads: so before anything imports it."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
