"""Untrusted videos: what their headers say, checked before any frame is decoded.

``probe_video`` reads the frame size, rate and duration from the container and codec headers and
decodes at most one frame, with these guards: only FFmpeg's mp4/mov, Matroska/WebM and AVI
demuxers ever see the file (chosen from its leading bytes, so FFmpeg never probes for another
one: playlists, image sequences and concat lists can make it read other files or URLs), only
through the file protocol, and every decoder refuses frames above ``max_side``² pixels (so a
file that lies in its headers cannot make one allocate more). ``probe_in_subprocess`` runs it in
a child process with a memory and time limit (the API does; ``python -m jobs probe FILE``).
``check_frame_budget`` refuses a job whose decoded frames would not fit its budget.

Imports only PyAV (no torch): the child starts in a fraction of a second.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

from jobs.child_env import child_environment

SAFE_CONTAINERS = {"mov": "mp4/mov", "matroska": "mkv/webm", "avi": "avi"}
_MOV_ATOMS = (b"ftyp", b"moov", b"mdat", b"free", b"skip", b"wide", b"pnot")


class VideoRejected(ValueError):
    """An untrusted file that is not an acceptable video; the message says why (never its path)."""


def sniff_container(head: bytes) -> str | None:
    """The FFmpeg demuxer (a key of ``SAFE_CONTAINERS``) for a file starting with ``head`` (its
    first 12 bytes or more), or None when it is none of them."""
    if len(head) >= 8 and head[4:8] in _MOV_ATOMS:
        return "mov"
    if head[:4] == b"\x1a\x45\xdf\xa3":
        return "matroska"
    if len(head) >= 12 and head[:4] == b"RIFF" and head[8:12] == b"AVI ":
        return "avi"
    return None


@dataclasses.dataclass(frozen=True)
class VideoInfo:
    """What a video's headers say. width, height: coded frame size (before any rotation);
    duration_s: seconds (from the headers, else from the packets' timestamps; None if neither);
    fps: the stream's average rate (0 if unknown); frames: the frame count if the headers give it."""

    container: str
    codec: str
    width: int
    height: int
    duration_s: float | None
    fps: float
    frames: int | None

    def frame_count(self) -> int | None:
        """Frames the video holds: its count, else duration x rate (None if neither is known)."""
        if self.frames:
            return self.frames
        if self.duration_s is not None and self.fps > 0:
            return max(1, math.ceil(self.duration_s * self.fps))
        return None


def probe_video(path: str | Path, max_side: int = 4096, decode_first: bool = True) -> VideoInfo:
    """Check an untrusted video (see the module docstring): a container of ``SAFE_CONTAINERS``,
    a video stream of at most ``max_side`` pixels a side, a known duration, and (with
    ``decode_first``) one decodable frame. Raises ``VideoRejected`` with the reason."""
    import av

    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as err:
        raise VideoRejected(f"the video cannot be read: {err.strerror}") from err
    if not head:
        raise VideoRejected("the uploaded video is empty (0 bytes)")
    demuxer = sniff_container(head)
    if demuxer is None:
        kinds = ", ".join(SAFE_CONTAINERS.values())
        raise VideoRejected(f"the upload is not a readable video (accepted containers: {kinds})")
    options = {"protocol_whitelist": "file", "max_pixels": str(max_side * max_side)}
    try:
        container = av.open(str(path), mode="r", format=demuxer, options=options)
    except (av.FFmpegError, OSError, ValueError) as err:
        raise VideoRejected(f"the upload is not a readable video: {_reason(err)}") from err
    with container:
        streams = container.streams.video
        if not streams:
            raise VideoRejected("the upload has no video stream")
        stream = streams[0]
        width, height = int(stream.codec_context.width or 0), int(stream.codec_context.height or 0)
        if width > max_side or height > max_side:
            raise VideoRejected(
                f"the video's frames are {width}x{height} pixels; the limit is {max_side} a side"
            )
        if width <= 0 or height <= 0:
            # Decoders zero the size they refuse (over max_pixels): a lying header ends here too.
            raise VideoRejected(f"the video's headers give no usable frame size (limit {max_side} a side)")
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        duration = None
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        elif container.duration is not None:
            duration = container.duration / 1e6
        if duration is None or duration <= 0:
            duration = _packet_span(container, stream)
        if duration is None:
            raise VideoRejected("the video's duration is unknown (no timestamps in its headers or packets)")
        info = VideoInfo(
            demuxer,
            stream.codec_context.name or "?",
            width,
            height,
            duration,
            float(rate) if rate else 0.0,
            int(stream.frames) or None,
        )
        if decode_first:
            stream.thread_type = "SLICE"  # one frame in flight, not one per thread
            try:
                frame = next(iter(container.decode(stream)), None)
            except (av.FFmpegError, OSError, ValueError) as err:
                raise VideoRejected(f"the upload could not be decoded: {_reason(err)}") from err
            if frame is None:
                raise VideoRejected("the upload holds no decodable video frame")
    return info


def _packet_span(container, stream) -> float | None:
    """Seconds from the first to the last packet timestamp (demuxed, not decoded)."""
    times = [float(p.pts * p.time_base) for p in container.demux(stream) if p.pts is not None and p.time_base]
    container.seek(0)
    return max(times) - min(times) if times else None


def _reason(err: Exception) -> str:
    """FFmpeg's message without the file name it appends."""
    return getattr(err, "strerror", None) or type(err).__name__


def decoded_pixels(info: VideoInfo, max_frames: int, max_size: int) -> int:
    """Frames x pixels that preprocessing decodes: ``max_frames`` (or fewer, if the video is
    shorter) frames, each resized so its longest side is at most ``max_size``."""
    frames = min(max_frames, info.frame_count() or max_frames)
    scale = min(1.0, max_size / max(info.width, info.height))
    return frames * max(1, round(info.width * scale)) * max(1, round(info.height * scale))


def check_frame_budget(info: VideoInfo, max_frames: int, max_size: int, budget: int) -> None:
    """Raise ``VideoRejected`` when the frames a job would decode exceed ``budget`` pixels."""
    pixels = decoded_pixels(info, max_frames, max_size)
    if pixels > budget:
        raise VideoRejected(
            f"{min(max_frames, info.frame_count() or max_frames)} frames of {info.width}x{info.height} "
            f"(resized to at most {max_size} px) are {pixels / 1e6:.0f} M pixels; the limit is "
            f"{budget / 1e6:.0f} M: lower max_frames or max_size"
        )


def probe_in_subprocess(
    path: Path, max_side: int = 4096, timeout_s: float = 30.0, memory_mb: int = 1024
) -> VideoInfo:
    """``probe_video`` in a child process limited to ``memory_mb`` of address space and
    ``timeout_s`` of wall time; whatever the file does to FFmpeg, the caller only sees
    ``VideoRejected``."""
    args = [
        sys.executable,
        "-m",
        "jobs",
        "probe",
        str(path),
        "--max-side",
        str(max_side),
        "--memory-mb",
        str(memory_mb),
    ]
    try:
        done = subprocess.run(
            args, capture_output=True, timeout=timeout_s, stdin=subprocess.DEVNULL, env=child_environment()
        )
    except subprocess.TimeoutExpired as err:  # run() has killed it
        raise VideoRejected(f"probing the video took longer than {timeout_s:.0f} s") from err
    try:
        answer = json.loads(done.stdout.decode().strip().splitlines()[-1])
    except (ValueError, IndexError):
        answer = None
    if not isinstance(answer, dict):
        raise VideoRejected(
            f"the video could not be probed within {memory_mb} MB (the probe exited with {done.returncode})"
        )
    if "error" in answer:
        raise VideoRejected(answer["error"])
    return VideoInfo(**answer["info"])


def _peak_rss_mb() -> float | None:
    """This process's peak resident memory (VmHWM; not ru_maxrss, which keeps the parent's from
    before exec)."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    return int(status.split("VmHWM:")[1].split()[0]) / 1024 if "VmHWM:" in status else None


def _limit_memory(memory_mb: int) -> None:
    import resource

    limit = memory_mb * 1024 * 1024
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Probe an untrusted video; one JSON line on stdout.")
    parser.add_argument("path", type=Path)
    parser.add_argument("--max-side", type=int, default=4096)
    parser.add_argument("--memory-mb", type=int, default=None)
    args = parser.parse_args(argv)
    if args.memory_mb:
        _limit_memory(args.memory_mb)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    try:
        answer: dict = {"info": dataclasses.asdict(probe_video(args.path, args.max_side))}
    except VideoRejected as err:
        answer = {"error": str(err)}
    answer["peak_rss_mb"] = _peak_rss_mb()
    print(json.dumps(answer), flush=True)
    return 0
