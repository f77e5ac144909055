"""Frames from any video file (mp4, mov, webm, avi, ...) with PyAV (FFmpeg), and a small writer.

    clip = read_video("talk.mp4", VideoReadOptions(every=2, max_frames=300, max_size=512))
    clip.frames      # [N, H, W, 3] uint8 RGB, display orientation
    clip.timestamps  # [N] seconds from the first frame of the stream

Rotation metadata (the container's display matrix, as phones write it) is applied, so frames
come out the way a player shows them. Anything that does not decode to at least one video frame
raises :class:`VideoError`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import torch


class VideoError(ValueError):
    """A file is missing, is not a video, or holds no decodable video frame."""


@dataclasses.dataclass(frozen=True)
class VideoReadOptions:
    """How to sample a video."""

    every: int = 1
    """Keep every k-th decoded frame (1 = all)."""
    max_frames: int | None = None
    """Stop after this many kept frames (None = no limit)."""
    max_size: int | None = None
    """Downscale so the longest side is at most this many pixels (never upscales)."""
    demuxer: str | None = None
    """Open the file with this FFmpeg demuxer only (e.g. the one an upload's check chose from its
    bytes), never the one FFmpeg would guess from its name or contents (None: guess)."""
    max_side: int | None = None
    """Refuse frames larger than this many pixels a side, from the headers or as each frame
    decodes, before its RGB copy (None: no limit)."""

    def __post_init__(self) -> None:
        if self.every < 1:
            raise ValueError(f"every must be >= 1, got {self.every}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {self.max_frames}")
        if self.max_size is not None and self.max_size < 1:
            raise ValueError(f"max_size must be >= 1, got {self.max_size}")
        if self.max_side is not None and self.max_side < 1:
            raise ValueError(f"max_side must be >= 1, got {self.max_side}")


@dataclasses.dataclass
class VideoClip:
    """Decoded frames. frames: [N, H, W, 3] uint8 RGB; timestamps: [N] float64 seconds (relative
    to the stream start); fps: the stream's average rate; rotation: counter-clockwise degrees
    applied from the display matrix; source_size: (height, width) of a displayed frame before
    resizing."""

    frames: np.ndarray
    timestamps: np.ndarray
    fps: float
    rotation: int
    source_size: tuple[int, int]

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def as_tensor(self) -> torch.Tensor:
        """[N, H, W, 3] float32 in [0, 1]."""
        return torch.from_numpy(self.frames).float().div_(255.0)


def _rotate(frame: np.ndarray, degrees: int) -> np.ndarray:
    """Rotate [H, W, 3] counter-clockwise by a multiple of 90 degrees."""
    k = int(round(degrees / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(frame, k)) if k else frame


def _resize(frame: np.ndarray, max_size: int | None) -> np.ndarray:
    import cv2

    h, w = frame.shape[:2]
    if max_size is None or max(h, w) <= max_size:
        return frame
    s = max_size / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


@dataclasses.dataclass
class _DecodedStream:
    """What decoding learnt about the stream besides its frames."""

    fps: float = 0.0
    rotation: int = 0
    source_size: tuple[int, int] = (0, 0)


def iter_frames(path: str | Path, options: VideoReadOptions | None = None) -> Iterator[np.ndarray]:
    """The frames ``read_video(path, options)`` returns, one at a time (RGB uint8 [H, W, 3]): a
    second pass over a video at another size without holding its frames."""
    for rgb, _ in _decode(path, options or VideoReadOptions(), _DecodedStream()):
        yield rgb


def iter_timed_frames(
    path: str | Path, options: VideoReadOptions | None = None
) -> Iterator[tuple[np.ndarray, float]]:
    """(frame, seconds) pairs as ``read_video(path, options)`` has them, one at a time."""
    yield from _decode(path, options or VideoReadOptions(), _DecodedStream())


def _decode(
    path: str | Path, opts: VideoReadOptions, stream_info: _DecodedStream
) -> Iterator[tuple[np.ndarray, float]]:
    """(frame, seconds from the stream's first frame) for each kept frame; fills ``stream_info``."""
    import av

    path = Path(path)
    if not path.is_file():
        raise VideoError(f"video file {path} does not exist")
    try:
        container = av.open(str(path), mode="r", format=opts.demuxer, options={"protocol_whitelist": "file"})
    except (av.FFmpegError, OSError, ValueError) as err:
        raise VideoError(f"{path} is not a readable video: {err}") from err
    kept = 0
    with container:
        streams = container.streams.video
        if not streams:
            raise VideoError(f"{path} has no video stream")
        stream = streams[0]
        _check_side(stream.codec_context.width or 0, stream.codec_context.height or 0, opts.max_side, path)
        stream.thread_type = "AUTO"
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        fps = float(rate) if rate else 0.0
        stream_info.fps = fps
        start = None
        decoded = 0
        try:
            for frame in container.decode(stream):
                if start is None:
                    start = frame.time if frame.time is not None else 0.0
                _check_side(frame.width, frame.height, opts.max_side, path)  # before its RGB copy
                keep = decoded % opts.every == 0
                decoded += 1
                if not keep:
                    continue
                t = frame.time if frame.time is not None else start + (decoded - 1) / (fps or 1.0)
                stream_info.rotation = int(frame.rotation or 0)
                rgb = _rotate(frame.to_ndarray(format="rgb24"), stream_info.rotation)
                stream_info.source_size = (int(rgb.shape[0]), int(rgb.shape[1]))
                kept += 1
                yield _resize(rgb, opts.max_size), float(t - start)
                if opts.max_frames is not None and kept >= opts.max_frames:
                    break
        except VideoError:
            raise
        except (av.FFmpegError, OSError, ValueError) as err:
            if not kept:
                raise VideoError(f"{path} could not be decoded: {err}") from err
            # A damaged tail: keep what decoded (players do the same).


def _check_side(width: int, height: int, max_side: int | None, path: Path) -> None:
    if max_side is not None and max(width, height) > max_side:
        raise VideoError(f"{path} has frames of {width}x{height} pixels; the limit is {max_side} a side")


def read_video(path: str | Path, options: VideoReadOptions | None = None) -> VideoClip:
    """Decode a video into RGB frames (see the module docstring). Raises :class:`VideoError`."""
    opts = options or VideoReadOptions()
    frames: list[np.ndarray] = []
    times: list[float] = []
    decoded = _DecodedStream()
    for rgb, t in _decode(path, opts, decoded):
        frames.append(rgb)
        times.append(t)
    fps, rotation, source_size = decoded.fps, decoded.rotation, decoded.source_size
    if not frames:
        raise VideoError(f"{path} holds no decodable video frame")
    if not fps and len(times) > 1:
        fps = (len(times) - 1) * opts.every / max(times[-1] - times[0], 1e-9)
    return VideoClip(
        frames=np.stack(frames),
        timestamps=np.asarray(times, dtype=np.float64),
        fps=fps,
        rotation=rotation,
        source_size=source_size,
    )


_CODECS = {".mp4": "libx264", ".mov": "libx264", ".mkv": "libx264", ".webm": "libvpx-vp9", ".avi": "mpeg4"}


def write_video(
    path: str | Path,
    frames: Sequence[np.ndarray] | np.ndarray,
    fps: float = 30.0,
    rotation: int = 0,
    quality: int = 18,
) -> Path:
    """Encode frames [N, H, W, 3] (uint8, or float in [0, 1]) as a video; the codec follows the
    suffix (.mp4/.mov/.mkv: H.264, .webm: VP9, .avi: MPEG-4). Odd sizes are padded by one edge
    pixel (4:2:0 chroma needs even sizes). ``rotation`` (counter-clockwise degrees, a multiple of
    90) is stored as display metadata, not applied to the pixels. ``quality``: the encoder's
    constant-quality value (lower is better). Returns ``path``."""
    import av

    path = Path(path)
    codec = _CODECS.get(path.suffix.lower())
    if codec is None:
        raise ValueError(f"unsupported video suffix {path.suffix!r}; use one of {sorted(_CODECS)}")
    if len(frames) == 0:
        raise ValueError("need at least one frame")
    if rotation % 90:
        raise ValueError(f"rotation must be a multiple of 90 degrees, got {rotation}")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise ValueError(f"frames must be [N, H, W, 3], got {arr.shape}")
    if arr.dtype != np.uint8:
        arr = np.clip(np.round(np.nan_to_num(arr.astype(np.float64)) * 255.0), 0, 255).astype(np.uint8)
    h, w = arr.shape[1:3]
    arr = np.pad(arr, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    from fractions import Fraction

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = int(arr.shape[2]), int(arr.shape[1])
        stream.pix_fmt = "yuv420p"
        if codec == "libx264":
            stream.options = {"crf": str(quality)}
        elif codec == "libvpx-vp9":
            stream.options = {"crf": str(quality + 12), "b": "0", "deadline": "realtime", "cpu-used": "8"}
        else:  # MPEG-4 part 2 has no constant-quality option here: a generous bit rate instead
            stream.bit_rate = 40 * stream.width * stream.height * int(round(fps))
        if rotation:
            stream.set_display_rotation(rotation)
        for a in arr:
            for packet in stream.encode(av.VideoFrame.from_ndarray(a, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path
