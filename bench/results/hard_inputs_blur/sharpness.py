"""Per-frame sharpness of datasets' training frames under the two measures tried (issue 41, blurred
frames at a low weight), and the weights the rule of ``sharp_frames_gradient.patch`` gives them.

    .venv/bin/python bench/results/hard_inputs_blur/sharpness.py --out bench/results/hard_inputs_blur \\
        <dataset> [<dataset> ...]

gradient: mean squared Sobel gradient over the grown person mask (the patch); crete_roffet:
Crete-Roffet et al.'s perceptual blur metric as 1 - blur (``sharp_frames_crete_roffet.patch``).
Weights: (sharpness / (0.8 * the clip's 90th percentile)) ** 2, clamped to [0.1, 1].
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from bench.machine import header_line, run_header, write_result  # noqa: E402
from eva_engine.data import load_dataset  # noqa: E402


def grown_masks(masks: torch.Tensor, px: int = 4) -> torch.Tensor:
    return F.max_pool2d((masks > 0.5).float()[:, None], 2 * px + 1, stride=1, padding=px)


def grey(images: torch.Tensor) -> torch.Tensor:
    return (images * images.new_tensor([0.299, 0.587, 0.114])).sum(-1)[:, None]


def gradient(images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    sobel = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]])
    g = F.conv2d(F.pad(grey(images), (1, 1, 1, 1), mode="replicate"), torch.stack([sobel, sobel.T])[:, None])
    region = grown_masks(masks)[:, 0]
    return ((g**2).sum(1) * region).sum((1, 2)) / region.sum((1, 2)).clamp(min=1.0)


def crete_roffet(images: torch.Tensor, masks: torch.Tensor, taps: int = 9) -> torch.Tensor:
    y, region, out = grey(images), grown_masks(masks), []
    for dim, size in ((3, (1, taps)), (2, (taps, 1))):
        pad = (taps // 2, taps // 2, 0, 0) if dim == 3 else (0, 0, taps // 2, taps // 2)
        d_image = y.diff(dim=dim).abs()
        d_blur = F.avg_pool2d(F.pad(y, pad, mode="replicate"), size, stride=1).diff(dim=dim).abs()
        inside = region.narrow(dim, 1, region.shape[dim] - 1)
        lost = ((d_image - d_blur).clamp(min=0.0) * inside).sum((1, 2, 3))
        out.append(lost / (d_image * inside).sum((1, 2, 3)).clamp(min=1e-12))
    return torch.minimum(*out)


def weights(s: torch.Tensor) -> torch.Tensor:
    return (s / (0.8 * torch.quantile(s, 0.9))).clamp(max=1.0).pow(2.0).clamp(min=0.1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("datasets", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    doc = {**run_header(), "datasets": {}}
    lines = [
        "# Training frames' sharpness, two measures",
        "",
        header_line(doc),
        "",
        "Per dataset, its training frames: each measure's range over its median (min-max), "
        "absolute range, and the weights of the patch's rule (frames below 1, mean, min).",
        "",
        "| dataset | frames | measure | relative range | absolute range | frames < 1 | mean weight "
        "| min weight |",
        "|---|---:|---|---|---|---:|---:|---:|",
    ]
    for path in args.datasets:
        ds = load_dataset(path)
        ids = list(ds.splits["train"])
        found: dict[str, list[torch.Tensor]] = {"gradient": [], "crete_roffet": []}
        for k in range(0, len(ids), 16):
            frames = [ds[i] for i in ids[k : k + 16]]
            images = torch.stack([f.image.float() for f in frames])
            masks = torch.stack([f.mask.float() for f in frames])
            found["gradient"].append(gradient(images, masks))
            found["crete_roffet"].append(crete_roffet(images, masks))
        name = path.parent.name if path.name == "dataset" else path.name
        for measure, parts in found.items():
            s = torch.cat(parts)
            w, rel = weights(s), s / s.median()
            row = {
                "frames": len(ids),
                "relative": [float(rel.min()), float(rel.max())],
                "absolute": [float(s.min()), float(s.max())],
                "below_one": int((w < 1).sum()),
                "mean_weight": float(w.mean()),
                "min_weight": float(w.min()),
            }
            doc["datasets"].setdefault(name, {})[measure] = row
            lines.append(
                f"| {name} | {len(ids)} | {measure} | {rel.min():.2f}-{rel.max():.2f} | "
                f"{s.min():.3g}-{s.max():.3g} | {row['below_one']} | {row['mean_weight']:.3f} | "
                f"{row['min_weight']:.3f} |"
            )
    write_result(args.out, "sharpness", doc, lines, show=True)


if __name__ == "__main__":
    main()
