"""Video uploads: a byte limit enforced while the request streams in (ASGI middleware), the copy
into the job's folder in chunks, and the checks that answer 4xx before a job is queued."""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from starlette.datastructures import UploadFile
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

CHUNK = 1024 * 1024
FORM_OVERHEAD = 64 * 1024  # multipart boundaries and the option fields around the file


class UploadTooLarge(Exception):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the upload is larger than the limit of {limit / 2**20:.0f} MB")
        self.limit = limit


class UploadLimit:
    """Stops a ``POST`` to a path matching ``path`` (a regular expression, whole path) whose body
    exceeds ``max_bytes`` (+ form overhead): at once from ``Content-Length``, else as soon as the
    streamed body crosses it."""

    def __init__(self, app: ASGIApp, path: str, max_bytes: int) -> None:
        self.app, self.path, self.max_bytes = app, re.compile(path), max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (scope["type"] != "http" or scope["method"] != "POST"
                or not self.path.fullmatch(scope["path"].rstrip("/"))):  # fmt: skip
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes + FORM_OVERHEAD
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > limit:
            err = UploadTooLarge(self.max_bytes)
            await JSONResponse({"detail": str(err)}, status_code=413)(scope, receive, send)
            return
        seen, over, replied = 0, False, False

        async def limited() -> Message:
            # Past the limit the body ends early: the app fails to parse it and answers, and
            # that answer is replaced by the 413 below (FastAPI turns errors raised here into 400).
            nonlocal seen, over
            if over:
                return {"type": "http.request", "body": b"", "more_body": False}
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    over = True
                    return {"type": "http.request", "body": b"", "more_body": False}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal replied
            if not over:
                await send(message)
            elif not replied:
                replied = True
                err = UploadTooLarge(self.max_bytes)
                await JSONResponse({"detail": str(err)}, status_code=413)(scope, receive, send)

        await self.app(scope, limited, guarded_send)


_SUFFIX = re.compile(r"^\.[a-z0-9]{1,5}$")


def safe_suffix(filename: str | None) -> str:
    """The upload's extension if it is harmless (helps the demuxer), else ``.video``."""
    suffix = Path(filename or "").suffix.lower()
    return suffix if _SUFFIX.match(suffix) else ".video"


async def save_upload(upload: UploadFile, dest: Path, max_bytes: int) -> int:
    """Copy the upload to ``dest`` in chunks; returns its size. Raises ``UploadTooLarge``."""
    size = 0
    with open(dest, "wb") as out:
        while chunk := await upload.read(CHUNK):
            size += len(chunk)
            if size > max_bytes:
                raise UploadTooLarge(max_bytes)
            out.write(chunk)
    return size


@dataclass
class VideoProbe:
    duration_s: float | None
    width: int
    height: int


def probe_video(path: Path, max_seconds: float) -> VideoProbe:
    """Check that ``path`` is a video with at least one decodable frame and not longer than
    ``max_seconds``. Raises ``eva_engine.data.VideoError`` with the reason."""
    import av

    from eva_engine.data import VideoError, VideoReadOptions, read_video

    duration = None
    try:
        with av.open(str(path), mode="r") as container:
            streams = container.streams.video
            if streams:
                stream = streams[0]
                if stream.duration is not None and stream.time_base is not None:
                    duration = float(stream.duration * stream.time_base)
                elif container.duration is not None:
                    duration = container.duration / 1e6
    except (av.FFmpegError, OSError, ValueError) as err:
        raise VideoError(f"the upload is not a readable video: {_hide(err, path)}") from err
    if duration is not None and duration > max_seconds:
        raise VideoError(f"the video is {duration:.1f} s long; the limit is {max_seconds:.0f} s")
    try:
        clip = read_video(path, VideoReadOptions(max_frames=1))  # raises for no decodable frame
    except VideoError as err:
        raise VideoError(_hide(err, path)) from err
    h, w = clip.frames.shape[1:3]
    return VideoProbe(duration, w, h)


def _hide(err: Exception, path: Path) -> str:
    """The error without the server's file path in it."""
    return str(err).replace(f"'{path}'", "the upload").replace(str(path), "the upload")


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
