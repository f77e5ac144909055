"""``JobsConfig``: where jobs live and how the queue behaves (shared by the API and the workers).

Layout under ``data_dir`` (a shared folder when workers run on several machines):

- ``avatars/<avatar_id>/``: finished avatars (``eva_engine.avatar`` files + ``frames.safetensors``);
- ``animations/<animation_id>/``: finished animations (``animation.mp4`` + ``animation.json``);
- ``jobs/jobs.db``: the job records (SQLite); ``jobs/queue.db``: huey's SQLite queue (default mode);
- ``jobs/work/<job_id>/``: a job's upload and intermediate results, removed when it ends.
"""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator


class JobsConfig(BaseModel):
    """data_dir: root of avatars and job files; queue_url: ``None`` or ``sqlite:///path`` for
    huey's SQLite queue (default ``<data_dir>/jobs/queue.db``), ``redis://host:port/db`` for Redis;
    max_attempts: runs of one job (a worker killed mid-job costs one); stale_after_s: a running
    job whose worker has not written a heartbeat for this long is taken back; heartbeat_s: how
    often a busy worker writes one; threads: torch CPU threads per job (None: torch's default).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    data_dir: Path
    queue_url: str | None = None
    queue_name: str = "eva"
    max_attempts: int = Field(2, ge=1, le=10)
    stale_after_s: float = Field(120.0, gt=0)
    heartbeat_s: float = Field(5.0, gt=0)
    threads: int | None = Field(None, ge=1)

    @field_validator("queue_url")
    @classmethod
    def _known_scheme(cls, url: str | None) -> str | None:
        if url is not None and not url.startswith(("redis://", "rediss://", "unix://", "sqlite://")):
            raise ValueError(f"queue URL {url!r} must start with redis://, rediss://, unix:// or sqlite://")
        return url

    @classmethod
    def from_env(cls, **overrides) -> JobsConfig:
        """Defaults from the environment: ``EVA_SERVICE_DIR`` (else ``eva_engine.paths.data_dir()``),
        ``EVA_QUEUE_URL``, ``EVA_JOB_THREADS``; ``overrides`` that are not None win."""
        from eva_engine.paths import data_dir

        env = {
            "data_dir": os.environ.get("EVA_SERVICE_DIR") or data_dir(),
            "queue_url": os.environ.get("EVA_QUEUE_URL") or None,
            "threads": os.environ.get("EVA_JOB_THREADS") or None,
        }
        env.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**env)

    @property
    def uses_redis(self) -> bool:
        return self.queue_url is not None and not self.queue_url.startswith("sqlite://")

    @property
    def avatars_dir(self) -> Path:
        return self.data_dir / "avatars"

    @property
    def animations_dir(self) -> Path:
        return self.data_dir / "animations"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    @property
    def work_dir(self) -> Path:
        return self.jobs_dir / "work"

    @property
    def db_path(self) -> Path:
        return self.jobs_dir / "jobs.db"

    @property
    def sqlite_queue_path(self) -> Path:
        if self.queue_url is not None and self.queue_url.startswith("sqlite://"):
            return Path(self.queue_url.removeprefix("sqlite://"))  # sqlite:///abs/path
        return self.jobs_dir / "queue.db"
