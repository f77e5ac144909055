"""Housekeeping: what crashes and lost races leave behind, removed after a time to live.

- ``jobs/work/<id>/`` of a job that has ended (its finisher removes it; a crash in between, or an
  attempt that lost its job and wrote on, can leave it), after ``FINISHED_GRACE_S``; of a job with
  no record (the API died during an upload), after ``orphan_ttl_s``;
- ``avatars/.deleted-*`` and ``animations/.deleted-*`` (a deletion that stopped between its
  rename and its removal);
- ``avatars/<id>/`` and ``animations/<id>/`` whose job failed or was cancelled, or whose record
  says they were deleted, after ``orphan_ttl_s``. One with *no* record is not removed but moved to
  ``quarantine/<avatars|animations>/<id>/``, where nothing removes it: a restore from a backup,
  a fresh job store or a wrong data dir must not cost a finished avatar (``docs/deployment.md``
  says how to put one back);
- uploads kept in a bucket (``jobs.storage_s3``) by the same rules as work folders;
- the records of failed and cancelled jobs, and of deleted avatars and animations,
  ``keep_records_days`` after they ended.

A worker sweeps at start and every ten minutes (``JobQueue``).
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from jobs.config import JobsConfig
from jobs.storage import Storage
from jobs.store import JobRecord, JobStore, is_valid_id

logger = logging.getLogger("eva.jobs")

FINISHED_GRACE_S = 60.0


@dataclass
class Sweep:
    """What one sweep removed: folders (paths), uploads in a bucket and job records (ids)."""

    folders: list[Path] = field(default_factory=list)
    uploads: list[str] = field(default_factory=list)
    records: list[str] = field(default_factory=list)
    quarantined: list[Path] = field(default_factory=list)  # where each went


def _age(path: Path, now: float) -> float:
    """Seconds since the folder or anything directly in it last changed."""
    try:
        times = [path.stat().st_mtime] + [p.stat().st_mtime for p in path.iterdir()]
    except OSError:
        return 0.0
    return now - max(times)


def _work_expired(job: JobRecord | None, age: float, config: JobsConfig) -> str | None:
    """Why a job's work (a folder, or its upload in a bucket) of this age goes, or None if it stays:
    its job ended a grace period ago, or it has no job past ``orphan_ttl_s``."""
    if job is not None and job.finished and age > FINISHED_GRACE_S:
        return f"of a {job.state} job"
    if job is None and age > config.orphan_ttl_s:
        return "without a job"
    return None


def sweep(config: JobsConfig, store: JobStore, storage: Storage, now: float | None = None) -> Sweep:
    """One pass (see the module docstring)."""
    now = time.time() if now is None else now
    done = Sweep()

    def remove(path: Path, why: str) -> None:
        shutil.rmtree(path, ignore_errors=True)
        done.folders.append(path)
        logger.info("swept %s (%s)", path, why)

    def quarantine(path: Path, into: Path) -> None:
        into.mkdir(parents=True, exist_ok=True)
        target = into / path.name
        if target.exists():  # quarantined before, and the same id came back: keep both
            target = into / f"{path.name}.{int(now)}"
        path.rename(target)
        done.quarantined.append(target)
        logger.warning("%s has no job record: moved to %s (not deleted)", path, target)

    for path in sorted(config.work_dir.iterdir()) if config.work_dir.is_dir() else []:
        job = store.get(path.name) if is_valid_id(path.name) else None
        why = _work_expired(job, _age(path, now), config)
        if why:
            remove(path, f"work folder {why}")
    for job_id, age in storage.remote_uploads(now):
        why = _work_expired(store.get(job_id), age, config)
        if why:
            storage.remove_work(job_id)
            done.uploads.append(job_id)
            logger.info("swept the upload of job %s from the bucket (%s)", job_id, why)
    for kind, folder in (("avatar", config.avatars_dir), ("animation", config.animations_dir)):
        for path in sorted(folder.iterdir()) if folder.is_dir() else []:
            age = _age(path, now)
            if path.name.startswith(".deleted-") and age > FINISHED_GRACE_S:
                remove(path, f"a deleted {kind}'s leftovers")
            elif is_valid_id(path.name) and age > config.orphan_ttl_s:
                job = store.by_output(path.name, with_deleted=True, kind=kind)
                if job is None:
                    quarantine(path, config.quarantine_dir / folder.name)
                elif job.state in ("failed", "cancelled") or job.output_deleted:
                    remove(path, f"{kind} of a {'deleted' if job.output_deleted else job.state} job")
    purged = store.purge(finished_before=now - config.keep_records_days * 86400.0)
    done.records = [job.id for job in purged]
    for job in purged:
        storage.remove_work(job.id)
    if done.folders or done.uploads or done.records or done.quarantined:
        logger.info(
            "sweep: removed %d folder(s), %d upload(s), %d record(s); quarantined %d folder(s)",
            len(done.folders),
            len(done.uploads),
            len(done.records),
            len(done.quarantined),
        )
    return done
