"""Avatar and work folders on disk. Ids are checked before they become paths, and a finished
avatar appears only by an atomic rename of a complete folder (never half-written); so does each
stage's result in a job's work folder (``move_into_place``). ``jobs.storage_s3.S3Storage`` keeps
the same things in a bucket, with this class's folders as its local cache."""

from __future__ import annotations

import errno
import os
import shutil
import uuid
from pathlib import Path

from jobs.config import JobsConfig
from jobs.store import is_valid_id


class StorageUnavailable(RuntimeError):
    """Where avatars and uploads are kept (a bucket) could not be reached or refused."""


class InvalidIdError(ValueError):
    """An id that is not 32 lowercase hex characters (e.g. one that tries path traversal)."""


def _checked(value: str, what: str) -> str:
    if not isinstance(value, str) or not is_valid_id(value):
        raise InvalidIdError(f"invalid {what} id {value!r}: ids are 32 lowercase hex characters")
    return value


class Storage:
    """Paths under ``JobsConfig.data_dir`` (see ``jobs.config``)."""

    def __init__(self, config: JobsConfig) -> None:
        self.config = config
        for folder in (config.avatars_dir, config.animations_dir, config.work_dir):
            folder.mkdir(parents=True, exist_ok=True)

    def avatar_dir(self, avatar_id: str) -> Path:
        return self.config.avatars_dir / _checked(avatar_id, "avatar")

    def work_dir(self, job_id: str) -> Path:
        return self.config.work_dir / _checked(job_id, "job")

    def avatar_exists(self, avatar_id: str) -> bool:
        return self.avatar_dir(avatar_id).is_dir()

    def publish(self, src: Path, avatar_id: str) -> Path:
        """Move the complete folder ``src`` (same file system) to the avatar's place atomically."""
        return publish_folder(src, self.avatar_dir(avatar_id), f"avatar {avatar_id}")

    def delete_avatar(self, avatar_id: str) -> None:
        """Remove an avatar; readers never see a partial folder."""
        remove_folder(self.avatar_dir(avatar_id))

    # -- animations (the same rules: checked ids, atomic publish, renamed away before removal) ---
    def animation_dir(self, animation_id: str) -> Path:
        return self.config.animations_dir / _checked(animation_id, "animation")

    def animation_exists(self, animation_id: str) -> bool:
        return self.animation_dir(animation_id).is_dir()

    def publish_animation(self, src: Path, animation_id: str) -> Path:
        return publish_folder(src, self.animation_dir(animation_id), f"animation {animation_id}")

    def delete_animation(self, animation_id: str) -> None:
        remove_folder(self.animation_dir(animation_id))

    # -- a job's upload (the work folder's ``input.*``) ----------------------------------------
    def save_upload(self, job_id: str) -> None:
        """The API has written the job's upload into its work folder: keep it where any worker
        can read it (here: it already is)."""

    def fetch_upload(self, job_id: str) -> Path:
        """The job's work folder, with its upload in it (here: it already is)."""
        return self.work_dir(job_id)

    def remote_uploads(self, now: float) -> list[tuple[str, float]]:
        """Uploads kept away from this host's work folders, as (job id, age in seconds) for the
        sweeper (here: none; the work folders are swept as folders)."""
        return []

    def remove_work(self, job_id: str) -> None:
        shutil.rmtree(self.work_dir(job_id), ignore_errors=True)


def publish_folder(src: Path, dst: Path, what: str) -> Path:
    if dst.exists():
        raise FileExistsError(f"{what} already exists")
    os.replace(src, dst)
    return dst


def remove_folder(path: Path) -> None:
    """Rename the folder away first, so readers never see it partial, then delete it."""
    if not path.exists():
        return
    trash = path.with_name(f".deleted-{path.name}-{uuid.uuid4().hex[:8]}")
    os.replace(path, trash)
    shutil.rmtree(trash, ignore_errors=True)


def input_file(work: Path) -> Path | None:
    """The upload in a job's work folder (``input.video`` or ``input.json``: ``service.uploads``), or None."""
    found = sorted(p for p in work.glob("input.*") if p.is_file()) if work.is_dir() else []
    return found[0] if found else None


def move_into_place(partial: Path, dest: Path) -> None:
    """Rename this attempt's complete folder to ``dest``; if another attempt got there first
    (its folder is just as complete), keep that one."""
    try:
        os.replace(partial, dest)
    except OSError as err:
        if err.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not dest.is_dir():
            raise
        shutil.rmtree(partial, ignore_errors=True)
