"""Video decoding: a video the test writes reads back (timestamps, subsampling, resizing,
rotation metadata); corrupt and non-video files raise VideoError."""

from __future__ import annotations

import numpy as np
import pytest

from eva_engine.data import VideoError, VideoReadOptions, read_video, write_video


def _frames(n: int = 10, h: int = 48, w: int = 64) -> np.ndarray:
    frames = np.zeros((n, h, w, 3), np.uint8)
    frames[:, :8, :8] = 255  # a white marker in the top-left corner
    for i in range(n):
        frames[i, 20:30, 30:40, 1] = 20 * i  # a patch whose brightness encodes the frame number
    return frames


@pytest.mark.parametrize("suffix", [".mp4", ".webm", ".avi", ".mov"])
def test_reads_what_it_wrote(tmp_path, suffix):
    frames = _frames()
    clip = read_video(write_video(tmp_path / f"v{suffix}", frames, fps=10))
    assert clip.frames.shape == frames.shape and clip.frames.dtype == np.uint8
    assert clip.fps == pytest.approx(10.0)
    np.testing.assert_allclose(clip.timestamps, np.arange(10) / 10.0, atol=1e-6)
    assert clip.frames[:, 2:6, 2:6].mean() > 240
    # Lossy codecs: the encoded frame number survives within a few grey levels.
    patch = clip.frames[:, 22:28, 32:38, 1].astype(float).mean(axis=(1, 2))
    np.testing.assert_allclose(patch, 20 * np.arange(10), atol=12)
    tensor = clip.as_tensor()
    assert tensor.shape == (10, 48, 64, 3) and 0.0 <= float(tensor.min()) and float(tensor.max()) <= 1.0


def test_subsample_and_resize(tmp_path):
    path = write_video(tmp_path / "v.mp4", _frames(), fps=10)
    clip = read_video(path, VideoReadOptions(every=3, max_frames=3, max_size=32))
    assert clip.frames.shape == (3, 24, 32, 3)
    np.testing.assert_allclose(clip.timestamps, [0.0, 0.3, 0.6], atol=1e-6)
    assert clip.source_size == (48, 64)
    assert read_video(path, VideoReadOptions(max_size=1000)).frames.shape[1:3] == (48, 64)  # never upscales


def test_rotation_metadata_is_applied(tmp_path):
    clip = read_video(write_video(tmp_path / "r.mp4", _frames(), fps=10, rotation=90))
    assert clip.rotation == 90
    assert clip.frames.shape == (10, 64, 48, 3)
    # 90 deg counter-clockwise: the top-left marker ends at the bottom-left.
    assert clip.frames[0, -6:, :6].mean() > 200 and clip.frames[0, :6, :6].mean() < 50


@pytest.mark.parametrize(
    "content",
    [b"", b"\x00" * 4096, b"this is a text file, not a video\n" * 20, b"\x1aE\xdf\xa3" + bytes(500)],
)
def test_rejects_non_videos(tmp_path, content):
    path = tmp_path / "bad.mp4"
    path.write_bytes(content)
    with pytest.raises(VideoError):
        read_video(path)


def test_rejects_truncated_and_missing(tmp_path):
    data = write_video(tmp_path / "v.mp4", _frames(), fps=10).read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 3])  # moov atom lost
    with pytest.raises(VideoError):
        read_video(tmp_path / "cut.mp4")
    with pytest.raises(VideoError, match="does not exist"):
        read_video(tmp_path / "nope.mp4")


def test_rejects_a_file_without_video(tmp_path):
    import av

    path = tmp_path / "audio.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("aac", rate=8000)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
        frame.sample_rate = 8000
        for p in s.encode(frame):
            c.mux(p)
        for p in s.encode():
            c.mux(p)
    with pytest.raises(VideoError, match="no video stream"):
        read_video(path)


def test_writer_validates_input(tmp_path):
    with pytest.raises(ValueError):
        write_video(tmp_path / "e.mp4", [])
    odd = write_video(tmp_path / "odd.mp4", np.zeros((2, 15, 17, 3), np.float32))
    assert read_video(odd).frames.shape[0] == 2


def _tga(width: int, height: int) -> bytes:
    """An uncompressed 24-bit TGA image: an 18-byte header, then the pixels (no magic bytes: FFmpeg
    takes a file for one by its name)."""
    header = bytes([0, 0, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0]) + width.to_bytes(2, "little")
    return header + height.to_bytes(2, "little") + bytes([24, 0]) + b"\x80" * (width * height * 3)


def test_a_named_demuxer_is_the_only_one_that_reads_the_file(tmp_path):
    """What the upload check approved is what decodes: with ``demuxer`` set, a file whose name
    (or contents) would make FFmpeg pick another demuxer is not read by that one."""
    image = tmp_path / "upload.tga"
    image.write_bytes(_tga(200, 100))
    assert read_video(image).frames.shape == (1, 100, 200, 3)  # guessed: the image demuxer
    with pytest.raises(VideoError, match="not a readable video"):
        read_video(image, VideoReadOptions(demuxer="mov"))
    # An MP4 under an image's name decodes as the MP4 it is.
    disguised = tmp_path / "clip.tga"
    disguised.write_bytes(write_video(tmp_path / "v.mp4", _frames(), fps=10).read_bytes())
    assert read_video(disguised, VideoReadOptions(demuxer="mov")).frames.shape == (10, 48, 64, 3)


def test_frames_over_the_size_limit_are_refused_by_the_decoder(tmp_path):
    path = write_video(tmp_path / "v.mp4", _frames(), fps=10)  # 64 x 48
    assert len(read_video(path, VideoReadOptions(demuxer="mov", max_side=64))) == 10
    with pytest.raises(VideoError):
        read_video(path, VideoReadOptions(demuxer="mov", max_side=40))
