"""``S3Storage``: avatars, animations and uploads in an S3-compatible bucket (AWS S3, MinIO, Ceph,
...), so that an upload taken by the API on one host is trained by a worker on another that shares
no disk with it, and its avatar rendered by any API host (``JobsConfig.storage_url``).

Keys, under ``s3://bucket/prefix/``:

- ``avatars/<id>/...`` and ``animations/<id>/...``: the published folder's files, then
  ``avatars/<id>/.published`` last. Only a folder with that marker exists (an upload cut short by
  a crash is never seen), and deleting removes the marker first, so readers never see it partial;
- ``work/<job_id>/input.*``: the job's upload, removed when the job ends.

Each host's ``data_dir`` (``Storage``'s folders) is a cache: a worker downloads the upload into its
own work folder and keeps its stages' results there (a job taken over by a worker on another host
starts again from the upload); an API host downloads an avatar on its first render. The bucket is
the truth: ``avatar_exists`` asks it, and drops a cached copy that it no longer has.
"""

from __future__ import annotations

import logging
import shutil
import uuid
from pathlib import Path

from jobs.config import JobsConfig
from jobs.storage import (
    Storage,
    StorageUnavailable,
    input_file,
    move_into_place,
    publish_folder,
    remove_folder,
)
from jobs.store import is_valid_id

logger = logging.getLogger("eva.jobs")

MARKER = ".published"


class S3Storage(Storage):
    """The bucket of ``config.storage_url`` (credentials: boto3's usual sources, e.g.
    ``AWS_ACCESS_KEY_ID`` / ``AWS_SECRET_ACCESS_KEY``), at ``config.s3_endpoint_url``."""

    def __init__(self, config: JobsConfig, client=None) -> None:
        super().__init__(config)
        if config.storage_url is None:
            raise ValueError("S3Storage needs JobsConfig.storage_url (s3://bucket[/prefix])")
        self.bucket, _, prefix = config.storage_url.removeprefix("s3://").partition("/")
        self.prefix = f"{prefix.strip('/')}/" if prefix.strip("/") else ""
        if client is None:
            try:
                import boto3
                from botocore.config import Config
            except ImportError as err:
                raise ValueError(
                    "storage in a bucket (EVA_STORAGE_URL) needs boto3: pip install 'eva-avatar[s3]'"
                ) from err

            retries = Config(
                retries={"max_attempts": 5, "mode": "standard"}, connect_timeout=10, read_timeout=60
            )
            client = boto3.client("s3", endpoint_url=config.s3_endpoint_url, config=retries)
        self.client = client  # boto3's clients are thread-safe: the API's render threads share it
        try:  # a wrong name would make every avatar look missing: fail at start instead
            self._call("open the bucket", self.client.head_bucket)
        except FileNotFoundError as err:
            raise StorageUnavailable(f"the storage bucket {self.bucket!r} does not exist") from err

    # -- keys and transfers --------------------------------------------------------------------
    def _key(self, *parts: str) -> str:
        return self.prefix + "/".join(parts)

    def _call(self, what: str, method, **kwargs):
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            return method(Bucket=self.bucket, **kwargs)
        except ClientError as err:
            if err.response.get("Error", {}).get("Code") in ("404", "NoSuchKey", "NotFound"):
                raise FileNotFoundError(f"{what}: not in the bucket") from err
            raise StorageUnavailable(f"the storage bucket refused to {what} ({err})") from err
        except BotoCoreError as err:
            raise StorageUnavailable(f"the storage bucket is unavailable ({type(err).__name__})") from err

    def _objects(self, folder: str) -> list[dict]:
        """Every object under ``folder/`` (a prefix that ends the folder's name): its listing entries."""
        objects, token = [], None
        while True:
            extra = {"ContinuationToken": token} if token else {}
            page = self._call("list", self.client.list_objects_v2, Prefix=folder + "/", **extra)
            objects += page.get("Contents", [])
            if not page.get("IsTruncated"):
                return objects
            token = page["NextContinuationToken"]

    def _keys(self, folder: str) -> list[str]:
        return [item["Key"] for item in self._objects(folder)]

    def _exists(self, key: str) -> bool:
        try:
            self._call("read", self.client.head_object, Key=key)
        except FileNotFoundError:
            return False
        return True

    def _put_folder(self, src: Path, folder: str) -> None:
        for path in sorted(p for p in src.rglob("*") if p.is_file()):
            with open(path, "rb") as body:
                rel = path.relative_to(src).as_posix()
                self._call("store a file", self.client.put_object, Key=f"{folder}/{rel}", Body=body)

    def _get_folder(self, folder: str, dst: Path, only=None) -> None:
        """Download ``folder``'s files (those ``only`` accepts) into ``dst``."""
        for key in self._keys(folder):
            rel = key[len(folder) + 1 :]
            if rel == MARKER or (only is not None and not only(rel)):
                continue
            if Path(rel).is_absolute() or ".." in Path(rel).parts:
                raise StorageUnavailable(f"the bucket holds an unsafe key {key!r}")
            target = dst / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            body = self._call("read a file", self.client.get_object, Key=key)["Body"]
            with open(target, "wb") as out:
                shutil.copyfileobj(body, out, 1 << 20)

    def _delete_keys(self, keys: list[str]) -> None:
        for start in range(0, len(keys), 1000):
            chunk = [{"Key": k} for k in keys[start : start + 1000]]
            self._call("delete", self.client.delete_objects, Delete={"Objects": chunk, "Quiet": True})

    # -- published folders: avatars and animations ---------------------------------------------
    def _published(self, kind: str, item_id: str, local: Path) -> bool:
        if self._exists(self._key(kind, item_id, MARKER)):
            return True
        if local.exists():  # deleted through another host: drop this host's copy
            remove_folder(local)
        return False

    def _cached(self, kind: str, item_id: str, local: Path) -> Path:
        """``local``, downloaded from the bucket first when this host has no copy."""
        if local.is_dir() or not self._exists(self._key(kind, item_id, MARKER)):
            return local
        partial = local.with_name(f".fetch-{item_id}-{uuid.uuid4().hex[:8]}")
        try:
            self._get_folder(self._key(kind, item_id), partial)
            move_into_place(partial, local)  # another thread may have fetched it first: keep that
        except FileNotFoundError:  # deleted while we read it: it no longer exists
            return local
        finally:
            shutil.rmtree(partial, ignore_errors=True)
        logger.info("fetched %s %s from the bucket", kind[:-1], item_id)
        return local

    def _publish_folder(self, kind: str, src: Path, item_id: str, local: Path) -> Path:
        folder = self._key(kind, item_id)
        if self._exists(f"{folder}/{MARKER}"):
            raise FileExistsError(f"{kind[:-1]} {item_id} already exists")
        self._put_folder(src, folder)
        self._call("publish", self.client.put_object, Key=f"{folder}/{MARKER}", Body=b"")
        if local.exists():  # a stale copy of a folder this id once had
            remove_folder(local)
        return publish_folder(src, local, f"{kind[:-1]} {item_id}")

    def _delete_folder(self, kind: str, item_id: str, local: Path) -> None:
        folder = self._key(kind, item_id)
        self._call("delete", self.client.delete_object, Key=f"{folder}/{MARKER}")  # invisible first
        self._delete_keys(self._keys(folder))
        remove_folder(local)

    def avatar_exists(self, avatar_id: str) -> bool:
        return self._published("avatars", avatar_id, super().avatar_dir(avatar_id))

    def avatar_dir(self, avatar_id: str) -> Path:
        return self._cached("avatars", avatar_id, super().avatar_dir(avatar_id))

    def publish(self, src: Path, avatar_id: str) -> Path:
        return self._publish_folder("avatars", src, avatar_id, super().avatar_dir(avatar_id))

    def delete_avatar(self, avatar_id: str) -> None:
        self._delete_folder("avatars", avatar_id, super().avatar_dir(avatar_id))

    def animation_exists(self, animation_id: str) -> bool:
        return self._published("animations", animation_id, super().animation_dir(animation_id))

    def animation_dir(self, animation_id: str) -> Path:
        return self._cached("animations", animation_id, super().animation_dir(animation_id))

    def publish_animation(self, src: Path, animation_id: str) -> Path:
        return self._publish_folder("animations", src, animation_id, super().animation_dir(animation_id))

    def delete_animation(self, animation_id: str) -> None:
        self._delete_folder("animations", animation_id, super().animation_dir(animation_id))

    # -- uploads -------------------------------------------------------------------------------
    def save_upload(self, job_id: str) -> None:
        work = self.work_dir(job_id)
        upload = input_file(work)
        if upload is None:
            raise FileNotFoundError(f"job {job_id} has no upload to store")
        with open(upload, "rb") as body:
            self._call(
                "store the upload",
                self.client.put_object,
                Key=self._key("work", job_id, upload.name),
                Body=body,
            )
        shutil.rmtree(work, ignore_errors=True)  # the bucket holds it now; a worker fetches it

    def fetch_upload(self, job_id: str) -> Path:
        work = self.work_dir(job_id)
        if input_file(work) is None:
            work.mkdir(parents=True, exist_ok=True)
            self._get_folder(self._key("work", job_id), work, only=lambda rel: rel.startswith("input."))
        return work

    def remote_uploads(self, now: float) -> list[tuple[str, float]]:
        newest: dict[str, float] = {}
        for item in self._objects(self._key("work")):
            job_id = item["Key"][len(self._key("work")) + 1 :].split("/", 1)[0]
            if is_valid_id(job_id):
                newest[job_id] = max(newest.get(job_id, 0.0), item["LastModified"].timestamp())
        return [(job_id, now - modified) for job_id, modified in sorted(newest.items())]

    def remove_work(self, job_id: str) -> None:
        super().remove_work(job_id)
        try:
            self._delete_keys(self._keys(self._key("work", job_id)))
        except StorageUnavailable:  # a leftover upload costs space, not a job: never fail for it
            logger.warning("job %s: its upload could not be removed from the bucket", job_id, exc_info=True)
