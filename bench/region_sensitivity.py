"""How much a hand or face score on real video is placement: each test frame's *target* scored
against itself moved by a few pixels, or blurred, with the evaluation's own crops and metrics.

    .venv/bin/python -m bench region_sensitivity --work data/real_videos_bs --scores real_videos

No avatar is involved: a shifted target is a perfect appearance placed ``r`` px off, a blurred
one a perfect placement without detail. Where the real-video table's hand or face score equals
the score of a shift of ``r`` px, the avatar is, on the metric's terms, as good as a perfect
copy misplaced by ``r`` px. The crops, per-frame means and frame means are those of
``eva_engine.eval.evaluate_avatar`` (``docs/evaluation.md``): the region masks of the product's
own preprocessing, each hand its own box, the test frames of ``bench/real_videos.py``'s datasets
(made here with the same settings when ``--work`` lacks them).

Shifts move the whole target by ``r`` px along each image axis, both ways (the mean of the four
is reported; edges replicated); blurs are Gaussian with standard deviation ``sigma`` px.
``--scores NAME`` adds the methods' region scores from ``bench/results/NAME.json`` beside them.

Writes ``bench/results/<name>.json`` and ``<name>.md``. Skips with a message when there are no
videos.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from bench.machine import header_line, run_header, write_result
from bench.real_videos import DEFAULT_VIDEOS, RESULTS, preprocess, videos_or_skip

SHIFTS_PX = (1, 2, 3, 4)
BLURS_PX = (0.5, 1.0, 1.5, 2.0)
DIRECTIONS = ((0, 1), (0, -1), (1, 0), (-1, 0))
REPORTED = ("lpips_vgg", "psnr")


def shifted(image: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """image [H, W, 3] moved by (dy, dx) px, edges replicated -> [H, W, 3]."""
    h, w = image.shape[:2]
    p = max(abs(dy), abs(dx))
    padded = F.pad(image.permute(2, 0, 1)[None], (p, p, p, p), mode="replicate")[0].permute(1, 2, 0)
    return padded[p - dy : p - dy + h, p - dx : p - dx + w]


def blurred(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """image [H, W, 3] under a Gaussian blur of ``sigma`` px -> [H, W, 3]."""
    out = cv2.GaussianBlur(image.numpy(), (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REPLICATE)
    return torch.from_numpy(np.ascontiguousarray(out))


def perturbations(target: torch.Tensor) -> dict[str, list[torch.Tensor]]:
    """{label: versions of ``target``} whose region scores are averaged under that label."""
    out = {f"shift {r} px": [shifted(target, dy * r, dx * r) for dy, dx in DIRECTIONS] for r in SHIFTS_PX}
    out.update({f"blur {s:g} px": [blurred(target, s)] for s in BLURS_PX})
    return out


def sensitivity(dataset, metrics) -> tuple[dict, dict[str, float]]:
    """({region: {label: {metric: mean over the frames of the frame's mean over its crops}}} on the
    test frames (``evaluate_avatar``'s aggregation), plus each region's frame count; {region:
    median box side in px}), from one pass over the test frames."""
    from eva_engine.eval.evaluate import REGION_MASKS, REGION_OF_MASK, box_side
    from eva_engine.train.losses import composite_target

    background = torch.ones(3)
    per_frame: dict[str, list[dict[str, dict[str, float]]]] = {"hand": [], "face": []}
    sides: dict[str, list[int]] = {"hand": [], "face": []}
    for i in dataset.splits["test_pose"]:
        frame = dataset[i]
        target = composite_target(frame.image.float(), frame.mask.float(), background)
        versions = perturbations(target)
        crops: dict[str, list[dict[str, dict[str, float]]]] = {"hand": [], "face": []}
        for name in REGION_MASKS:
            mask = frame.regions.get(name)
            if mask is None or not bool((mask > 0.5).any()):
                continue
            scores = {}
            for label, images in versions.items():
                rows = [metrics(img, target, mask) for img in images]
                scores[label] = {m: statistics.mean(r[m] for r in rows) for m in REPORTED}
            crops[REGION_OF_MASK[name]].append(scores)
            sides[REGION_OF_MASK[name]].append(box_side(mask))
        for region, found in crops.items():
            if found:
                per_frame[region].append(
                    {
                        label: {m: statistics.mean(c[label][m] for c in found) for m in REPORTED}
                        for label in found[0]
                    }
                )
    out: dict = {}
    for region, frames in per_frame.items():
        if not frames:
            continue
        out[region] = {
            label: {m: statistics.mean(f[label][m] for f in frames) for m in REPORTED} for label in frames[0]
        }
        out[region]["frames"] = len(frames)
    return out, {r: float(statistics.median(v)) for r, v in sides.items() if v}


def method_scores(name: str | None, video: str) -> dict[str, dict[str, dict[str, float]]]:
    """{method: {region: {metric: value}}} of ``bench/results/<name>.json`` for ``video``
    (empty without a name)."""
    if not name:
        return {}
    doc = json.loads((RESULTS / f"{name}.json").read_text())
    methods = doc["videos"].get(video, {}).get("methods", {})
    return {
        m: {r: {k: e[r][k] for k in REPORTED} for r in ("hand", "face") if r in e} for m, e in methods.items()
    }


def markdown(doc: dict) -> str:
    lines = [
        "# How much of a region score is placement",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        "",
        "Each test frame's target (the person composited on white) scored against itself shifted by"
        " r px (mean of the four axis directions) or blurred (Gaussian, sigma px), on the evaluation's"
        " own hand and face crops (`bench/real_videos.py`'s datasets, long side 512 px). LPIPS-VGG ×1000"
        " and PSNR. No avatar is involved.",
    ]
    if doc["scores"]:
        source = f"bench/results/{doc['scores']}.md"
        lines.append(f"Methods' scores from `{source}` (same crops, same test frames).")
    for video, entry in doc["videos"].items():
        lines += ["", f"## {video}", ""]
        regions = [r for r in ("hand", "face") if r in entry["regions"]]
        head = "| target against itself | " + " | ".join(f"{r} LPIPS-VGG | {r} PSNR" for r in regions)
        lines += [head + " |", "|---|" + "---:|---:|" * len(regions)]
        labels = [k for k in entry["regions"][regions[0]] if k != "frames"] if regions else []
        for label in labels:
            rows = [entry["regions"][r][label] for r in regions]
            cells = [f"{1000 * row['lpips_vgg']:.1f} | {row['psnr']:.2f}" for row in rows]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        for method, scores in entry["methods"].items():
            rows = [scores.get(r, {"lpips_vgg": float("nan"), "psnr": float("nan")}) for r in regions]
            cells = [f"{1000 * row['lpips_vgg']:.1f} | {row['psnr']:.2f}" for row in rows]
            lines.append(f"| {method} (its avatar) | " + " | ".join(cells) + " |")
        frames = ", ".join(f"{r} {entry['regions'][r]['frames']}" for r in regions)
        sizes = ", ".join(f"{k} {v:.0f} px" for k, v in entry["box_px"].items())
        lines += ["", f"Test frames scored: {frames}; median box side: {sizes}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--videos", type=Path, default=DEFAULT_VIDEOS, help="folder of videos")
    ap.add_argument("--work", type=Path, help="the real-video datasets (default: <data dir>/real_videos)")
    ap.add_argument("--frames", type=int, default=280)
    ap.add_argument("--max-size", type=int, default=512)
    ap.add_argument("--detect-max-size", type=int, default=1280)
    ap.add_argument("--scores", help="a bench/real_videos.py result name to set beside (e.g. real_videos)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="region_sensitivity")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    videos = videos_or_skip(args.videos)
    if not videos:
        return

    from eva_engine.data import load_dataset
    from eva_engine.eval import ImageMetrics
    from eva_engine.paths import data_dir

    torch.set_num_threads(args.threads)
    work = args.work or data_dir() / "real_videos"
    metrics = ImageMetrics()
    doc = {
        **run_header(),
        "shifts_px": list(SHIFTS_PX),
        "blurs_px": list(BLURS_PX),
        "scores": args.scores,
        "videos": {},
    }
    for video in videos:
        print(f"{video.name} ...", file=sys.stderr, flush=True)
        folder = work / video.stem / "dataset"
        preprocess(video, folder, args.frames, args.max_size, args.detect_max_size)
        regions, box_px = sensitivity(load_dataset(folder), metrics)
        doc["videos"][video.name] = {
            "regions": regions,
            "box_px": box_px,
            "methods": method_scores(args.scores, video.name),
        }
    args.out.mkdir(parents=True, exist_ok=True)
    write_result(args.out, args.name, doc, markdown(doc))
    print(markdown(doc))


if __name__ == "__main__":
    main()
