"""Where the job records and the files live, from the configuration: ``open_store`` (SQLite on
this host, or Redis) and ``open_storage`` (this host's disk, or an S3-compatible bucket)."""

from __future__ import annotations

from jobs.config import JobsConfig
from jobs.storage import Storage
from jobs.store import JobStore, SqliteJobStore


def open_store(config: JobsConfig) -> JobStore:
    if config.records_url is not None:
        from jobs.store_redis import RedisJobStore

        return RedisJobStore(config.records_url, prefix=f"{config.queue_name}:records")
    return SqliteJobStore(config.db_path)


def open_storage(config: JobsConfig) -> Storage:
    if config.storage_url is not None:
        from jobs.storage_s3 import S3Storage

        return S3Storage(config)
    return Storage(config)
