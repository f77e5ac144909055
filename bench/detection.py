"""How often MediaPipe Holistic finds each hand and the face in the reference videos, by the size
of the frames it is given (``PreprocessConfig.detect_max_size``).

    .venv/bin/python -m bench detection                 # ../shared/reference/videos (skips if absent)
    .venv/bin/python -m bench detection --videos DIR --sizes 512 1280

Each video is sampled as ``bench/real_videos.py`` samples it (about ``--frames`` frames, every
k-th), and every size runs the detector in video mode over the same frames, resized so their long
side is at most that size (never upscaled). Writes ``bench/results/detection.{json,md}``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from bench.machine import header_line, run_header, write_result
from bench.real_videos import DEFAULT_VIDEOS, frame_count, videos_or_skip

RESULTS = Path(__file__).resolve().parent / "results"
PARTS = ("pose", "left_hand", "right_hand", "face")


def measure(video: Path, frames: int, size: int) -> dict:
    from eva_engine.align import detect_frames
    from eva_engine.data import VideoReadOptions, iter_frames

    every = max(1, math.ceil(frame_count(video) / frames))
    started = time.perf_counter()
    det = detect_frames(iter_frames(video, VideoReadOptions(every, frames, size)))
    seconds = time.perf_counter() - started
    n = len(det.found)
    return {"frames": n, "every": every, "rates": det.rates(), "ms_per_frame": 1000 * seconds / max(n, 1)}


def markdown(doc: dict) -> str:
    lines = [
        "# Detection rates by the detector's frame size",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        "- MediaPipe Holistic 0.10.21 (model_complexity 1, video mode, refined face); each size gets "
        "the same frames, resized so the long side is at most that size (never upscaled). "
        "ms/frame includes decoding.",
        "",
        "| video | source | size | frames | pose | left hand | right hand | face | ms/frame |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, v in doc["videos"].items():
        for size, r in v["sizes"].items():
            rates = " | ".join(f"{100 * r['rates'][p]:.0f}%" for p in PARTS)
            source = f"{v['source'][1]}x{v['source'][0]}"
            ms = r["ms_per_frame"]
            lines.append(f"| {name} | {source} | {size} | {r['frames']} | {rates} | {ms:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--videos", type=Path, default=DEFAULT_VIDEOS, help="folder of videos")
    ap.add_argument("--frames", type=int, default=280, help="frames to sample per video")
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 768, 1024, 1280, 1920])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="detection", help="result file stem")
    args = ap.parse_args(argv)
    videos = videos_or_skip(args.videos)
    if not videos:
        return
    import torch

    from eva_engine.data import VideoReadOptions, read_video

    torch.set_num_threads(args.threads)
    doc = {
        **run_header(),
        "videos": {},
    }
    for video in videos:
        source = read_video(video, VideoReadOptions(max_frames=1)).source_size
        sizes = sorted({min(s, max(source)) for s in args.sizes})  # sizes past the source repeat it
        entry = {"source": list(source), "sizes": {}}
        for size in sizes:
            print(f"{video.name} at {size} px ...", file=sys.stderr, flush=True)
            entry["sizes"][str(size)] = measure(video, args.frames, size)
        doc["videos"][video.name] = entry
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_result(RESULTS, args.name, doc, markdown(doc))
    print(markdown(doc))


if __name__ == "__main__":
    main()
