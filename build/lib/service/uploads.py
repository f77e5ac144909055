"""Uploads: the job's folder they go into (``queued_job``), the copy, and the checks that answer 4xx
before a job is queued (headers probed in a child process, frame budget). Blocking: routers run
them in a thread. The body's size limit is the request guard's (``service.guard``)."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from jobs.media import VideoInfo, VideoRejected, check_frame_budget, probe_in_subprocess
from jobs.options import MIN_FRAMES, JobOptions
from jobs.store import new_id

if TYPE_CHECKING:
    from jobs.animation import AnimationOptions
    from jobs.queue import JobQueue
    from service.settings import ServiceSettings

CHUNK = 1024 * 1024


class UploadTooLarge(Exception):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the upload is larger than the limit of {limit / 2**20:.0f} MB")
        self.limit = limit


# Uploads are stored under neutral names: the user's extension never reaches a demuxer (the job
# decodes with the one the probe chose from the file's bytes), nor the file system.
VIDEO_UPLOAD, POSES_UPLOAD = "input.video", "input.json"


def save_upload(source: BinaryIO, dest: Path, max_bytes: int) -> int:
    """Copy the spooled upload to ``dest`` in chunks; returns its size. Raises ``UploadTooLarge``."""
    size = 0
    source.seek(0)
    with open(dest, "wb") as out:
        while chunk := source.read(CHUNK):
            size += len(chunk)
            if size > max_bytes:
                raise UploadTooLarge(max_bytes)
            out.write(chunk)
    return size


def check_video(path: Path, options: JobOptions | AnimationOptions, settings: ServiceSettings) -> VideoInfo:
    """The upload's headers, probed in a child process (``settings.probe_timeout_s``,
    ``settings.probe_memory_mb``): a safe container, frames of at most ``jobs.max_video_side``, at
    most ``settings.max_video_seconds`` long, one decodable frame, and decoded frames
    (``options.max_frames`` of at most ``options.max_size``: an avatar's video or an animation's
    driving video) within ``jobs.max_frame_pixels``; an avatar's video, at least ``MIN_FRAMES``
    frames. Raises ``VideoRejected`` with the reason."""
    jobs = settings.jobs
    info = probe_in_subprocess(path, jobs.max_video_side, settings.probe_timeout_s, settings.probe_memory_mb)
    if info.duration_s is not None and info.duration_s > settings.max_video_seconds:
        limit = settings.max_video_seconds
        raise VideoRejected(f"the video is {info.duration_s:.1f} s long; the limit is {limit:.0f} s")
    frames = info.frame_count()
    if isinstance(options, JobOptions) and frames is not None and frames < MIN_FRAMES:
        raise VideoRejected(
            f"the video has {frames} frame{'s' if frames != 1 else ''}; an avatar needs at least {MIN_FRAMES}"
        )
    check_frame_budget(info, options.max_frames, options.max_size, jobs.max_frame_pixels)
    return info


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


@contextmanager
def queued_job(queue: JobQueue) -> Iterator[tuple[str, Path]]:
    """A new job id and its empty work folder for the ``with`` body, which saves the upload, checks
    it and creates the job's record; then the job is queued. When the body or the queue fails,
    nothing stays behind: the folder goes (and the record, when the queue backend is down)."""
    job_id = new_id()
    work = queue.storage.work_dir(job_id)
    work.mkdir(parents=True)
    try:
        yield job_id, work
    except BaseException:
        remove_tree(work)
        raise
    try:
        queue.storage.save_upload(job_id)
        queue.enqueue(job_id)
    except BaseException:
        queue.store.delete(job_id)
        queue.storage.remove_work(job_id)
        raise
