"""What the quality report costs a job: the job path's stages on one video at the job defaults
(``JobOptions()``), each timed: preprocess (with the held-out frames ``held_out_every`` picks),
train, the quality report (``eval.quality_report``: the held-out frames scored, the detection
summary), and the training-frame metrics the job also measures. Writes
``bench/results/quality_cost.{json,md}``; skips with a message without the reference videos.

    .venv/bin/python -m bench quality_cost            # latentsync_demo3_gesturing.mp4
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result

ROOT = Path(__file__).resolve().parents[1]
VIDEOS = ROOT.parent / "shared" / "reference" / "videos"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--video", default="latentsync_demo3_gesturing.mp4")
    ap.add_argument("--videos", type=Path, default=VIDEOS)
    ap.add_argument("--work", type=Path, default=ROOT / "data" / "quality_cost")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    args = ap.parse_args(argv)
    video = args.videos / args.video
    if not video.is_file():
        print(f"skipped: {video} is absent (the reference videos are not beside this checkout)")
        return
    torch.set_num_threads(args.threads)

    from eva_engine.align import preprocess_video
    from eva_engine.data import load_dataset
    from eva_engine.eval import ImageMetrics, quality_report
    from eva_engine.train import preset, train_avatar
    from jobs.avatar import _training_metrics
    from jobs.media import probe_video
    from jobs.options import JobOptions

    options = JobOptions()
    config = options.preprocess_config(probe_video(video, 4096, decode_first=False).frame_count())
    seconds: dict[str, float] = {}
    start = time.perf_counter()
    preprocess_video(video, args.work / "dataset", config, overwrite=True)
    seconds["preprocess"] = time.perf_counter() - start
    ds = load_dataset(args.work / "dataset")
    start = time.perf_counter()
    result = train_avatar(ds, preset(options.preset))
    seconds["train"] = time.perf_counter() - start
    start = time.perf_counter()
    metrics = ImageMetrics()
    quality = quality_report(result.avatar, ds, metrics)
    seconds["quality_report"] = time.perf_counter() - start
    start = time.perf_counter()
    fit = _training_metrics(result.avatar, ds, metrics)
    seconds["training_metrics"] = time.perf_counter() - start
    total = sum(seconds.values())
    doc = {
        **run_header(),
        "video": args.video,
        "options": options.model_dump(),
        "frames": len(ds),
        "held_out": len(ds.splits.get("test_pose", [])),
        "seconds": seconds,
        "quality_share": seconds["quality_report"] / total,
        "quality": quality.model_dump(),
        "training_metrics": fit,
    }
    held = quality.held_out
    lines = [
        "# What the quality report costs a job",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- video: {args.video}, the job defaults ({options.preset} preset, {options.max_frames} frames at "
        f"most, {options.max_size} px): {doc['frames']} frames, {doc['held_out']} held out",
        "",
        "| stage | seconds | share of the job |",
        "|---|---:|---:|",
        *[f"| {k} | {v:.1f} | {100 * v / total:.1f}% |" for k, v in seconds.items()],
        f"| total | {total:.1f} | 100% |",
        "",
        "Held-out scores (full image): "
        + (
            f"PSNR {held.psnr:.2f}, LPIPS-VGG ×1000 {1000 * held.lpips_vgg:.1f}, "
            f"silhouette IoU {held.silhouette_iou:.3f}, debris {held.debris:.3f}"
            if held is not None and held.psnr is not None and held.lpips_vgg is not None
            else "none"
        )
        + ". The whole report is in the JSON.",
        "",
    ]
    write_result(args.out, "quality_cost", doc, lines, show=True)


if __name__ == "__main__":
    main()
