"""``JobsConfig``: where jobs live and how the queue behaves (shared by the API and the workers).

Layout under ``data_dir`` (a shared folder when workers run on several machines):

- ``avatars/<avatar_id>/``: finished avatars (avatar directories, ``eva_engine.avatar.io``);
- ``animations/<animation_id>/``: finished animations (``animation.mp4`` + ``animation.json``);
- ``jobs/jobs.db``: the job records (SQLite); ``jobs/queue.db``: huey's SQLite queue (default mode);
- ``jobs/work/<job_id>/``: a job's upload and intermediate results, removed when it ends;
- ``quarantine/``: avatars and animations found without a job record (never removed by the service).

On several hosts (``docs/deployment.md``), nothing is shared but Redis and a bucket: with
``records_url`` the job records live in Redis (``jobs.store_redis``), with ``storage_url`` the
avatars, animations and uploads live in an S3-compatible bucket (``jobs.storage_s3``), and each
host's ``data_dir`` holds only its cache of them and its own work folders.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from eva_engine.paths import data_dir as engine_data_dir

ENV_PREFIX = "EVA_"


class JobsConfig(BaseSettings):
    """data_dir: root of avatars and job files; queue_url: ``None`` or ``sqlite:///path`` for
    huey's SQLite queue (default ``<data_dir>/jobs/queue.db``), ``redis://host:port/db`` for Redis;
    max_attempts: runs of one job that may end in a crash of its own process (killed, out of
    memory); max_worker_losses: runs of one job that may end because the worker under it died
    (its host or container went away: not the job's doing, so a more generous count, after which
    the job fails rather than loop for ever); stale_after_s: a running
    job whose worker has not written a heartbeat for this long is taken back (when the worker ran
    on another host; on the same host its process is checked instead); heartbeat_s: how often a
    busy worker writes one; threads: torch CPU threads per job (None: torch's default).

    Limits of one job, which runs in its own process: job_memory_mb, its address-space limit
    (``RLIMIT_AS``; None: none); job_timeout_s, its wall time; max_frame_pixels, decoded frames
    x pixels per frame (checked at upload and again before decoding); max_video_side, largest
    width or height of an input video, read from its headers; max_gaussians, cap on the
    avatar's Gaussians during training; max_gaussian_std_m, bound on every Gaussian's standard
    deviation in metres (``AvatarConfig.max_scale``, None: unbounded; at 10 cm no difference in
    held-out quality, ``bench/results/hard_inputs.md``). Housekeeping: requeue_after_s, a queued job with no
    message in the queue for this long is sent again; orphan_ttl_s, age after which work folders
    without a live job are removed; keep_records_days, failed / cancelled / deleted jobs' records
    are kept this long.

    Every field can be set from the environment as ``EVA_<FIELD>`` (``EVA_QUEUE_URL``,
    ``EVA_MAX_ATTEMPTS``, ...; empty values are ignored), but two keep their older names:
    ``data_dir`` is ``EVA_SERVICE_DIR`` (default: ``eva_engine.paths.data_dir()``, which
    ``EVA_DATA_DIR`` sets) and ``threads`` is ``EVA_JOB_THREADS``. ``EVA_JOB_MEMORY_MB=0`` is
    no limit. Arguments given to the constructor win over the environment
    (``docs/configuration.md`` lists every variable).
    """

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX, env_ignore_empty=True, extra="forbid", frozen=True, populate_by_name=True
    )

    data_dir: Path = Field(default_factory=engine_data_dir, validation_alias="EVA_SERVICE_DIR")
    queue_url: str | None = None
    queue_name: str = "eva"
    max_attempts: int = Field(2, ge=1, le=10)
    max_worker_losses: int = Field(5, ge=1, le=50)
    stale_after_s: float = Field(120.0, gt=0)
    heartbeat_s: float = Field(5.0, gt=0)
    threads: int | None = Field(None, ge=1, validation_alias="EVA_JOB_THREADS")
    records_url: str | None = None
    storage_url: str | None = None
    s3_endpoint_url: str | None = None
    job_memory_mb: int | None = Field(8192, ge=256)
    job_timeout_s: float = Field(6 * 3600.0, gt=0)
    max_frame_pixels: int = Field(150_000_000, ge=64 * 64)
    max_video_side: int = Field(4096, ge=64, le=16384)
    max_gaussians: int = Field(300_000, ge=1000)
    max_gaussian_std_m: float | None = Field(0.10, gt=0)
    requeue_after_s: float = Field(300.0, gt=0)
    orphan_ttl_s: float = Field(6 * 3600.0, gt=0)
    keep_records_days: float = Field(30.0, gt=0)

    @field_validator("queue_url")
    @classmethod
    def _known_scheme(cls, url: str | None) -> str | None:
        if url is not None and not url.startswith(("redis://", "rediss://", "unix://", "sqlite://")):
            raise ValueError(f"queue URL {url!r} must start with redis://, rediss://, unix:// or sqlite://")
        return url

    @field_validator("records_url")
    @classmethod
    def _redis_records(cls, url: str | None) -> str | None:
        if url is not None and not url.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"records URL {url!r} must start with redis://, rediss:// or unix://")
        return url

    @field_validator("storage_url")
    @classmethod
    def _bucket(cls, url: str | None) -> str | None:
        if url is not None and (not url.startswith("s3://") or not url.removeprefix("s3://").strip("/")):
            raise ValueError(f"storage URL {url!r} must be s3://bucket or s3://bucket/prefix")
        return url

    @field_validator("job_memory_mb", mode="before")
    @classmethod
    def _zero_is_no_limit(cls, value):
        return None if value in (0, "0") else value

    @classmethod
    def from_env(cls, **overrides) -> JobsConfig:
        """The environment's configuration (class docstring), with ``overrides`` that are not None."""
        return cls(**{k: v for k, v in overrides.items() if v is not None})

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
    def quarantine_dir(self) -> Path:
        """Avatars and animations the sweeper found without a job record (``jobs.sweep``)."""
        return self.data_dir / "quarantine"

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
