"""Avatar evaluation as in the paper's Table 1: PSNR / SSIM / LPIPS on the full image and on the
hand and face regions of novel-pose test frames, plus Gaussian count, training time, render FPS.

Protocol (documented choices):
- target = the test frame's person composited on the render background (the avatar models the
  person, not the scene), prediction = the avatar rendered with the frame's body parameters and
  camera (``dataset.params``; ``dataset.gt_params`` when a dataset has only ground truth);
- full: the metrics on the whole image;
- hand / face: the metrics on the crop to the region mask's bounding box (grown by ``pad``, and
  to at least 32 px so LPIPS(alex) and SSIM are defined); frames whose region is empty are
  skipped for that region (the count is reported);
- LPIPS is stored as is; the markdown table prints it x1000 like the paper.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import torch
from torch import Tensor

from eva_engine.avatar import Avatar, Camera
from eva_engine.metrics import LPIPS, crop_to_mask_bbox, psnr, ssim

REGIONS = ("full", "hand", "face")
MIN_CROP = 32


@dataclass
class RegionMetrics:
    """Means over the frames that show the region."""

    psnr: float
    ssim: float
    lpips: float
    frames: int


@dataclass
class EvalResult:
    """One avatar on one split. regions: "full", "hand", "face" -> metrics (a region no frame
    shows is absent); per_frame: frame index -> region -> {psnr, ssim, lpips}."""

    split: str
    num_frames: int
    regions: dict[str, RegionMetrics]
    num_gaussians: int
    render_fps: float
    train_seconds: float | None = None
    per_frame: dict[int, dict[str, dict[str, float]]] = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["per_frame"] = {str(k): v for k, v in self.per_frame.items()}
        return d


def image_metrics(
    pred: Tensor, target: Tensor, lpips: LPIPS, mask: Tensor | None = None, pad: int = 4
) -> dict:
    """pred, target: [H, W, 3]; mask: [H, W] region (None: full image) -> {psnr, ssim, lpips}, or
    {} when the region is empty."""
    a, b = pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
    if mask is not None:
        m = mask[None, None]
        if not bool((m > 0.5).any()):
            return {}
        a, b = crop_to_mask_bbox(a, b, mask=m, pad=pad, min_size=MIN_CROP)
    return {"psnr": float(psnr(a, b)[0]), "ssim": float(ssim(a, b)[0]), "lpips": float(lpips(a, b)[0])}


def _eval_params(dataset):
    params = dataset.params if dataset.params is not None else getattr(dataset, "gt_params", None)
    if params is None:
        raise ValueError("the dataset has no body parameters to drive the avatar (params or ground truth)")
    return params


@torch.no_grad()
def evaluate_avatar(
    avatar: Avatar,
    dataset,
    split: str = "test_pose",
    lpips: LPIPS | None = None,
    background: Tensor | None = None,
    train_seconds: float | None = None,
) -> EvalResult:
    """Evaluate ``avatar`` on ``dataset.splits[split]`` (see the module docstring)."""
    from eva_engine.train.losses import composite_target

    indices = list(dataset.splits.get(split, []))
    if not indices:
        raise ValueError(f"the dataset has no frames in split {split!r}")
    params = _eval_params(dataset)
    lpips = lpips or LPIPS()
    if background is None:
        bg = getattr(dataset.meta, "background", None)
        background = torch.tensor(bg if bg is not None else (1.0, 1.0, 1.0), dtype=torch.float32)
    avatar.eval()
    device = avatar.shape.device
    per_frame: dict[int, dict[str, dict[str, float]]] = {}
    render_time = 0.0
    for i in indices:
        frame = dataset[i]
        h, w = frame.image.shape[:2]
        cam = Camera(frame.K.float(), frame.viewmat.float(), w, h)
        t0 = time.perf_counter()
        pred = avatar(params[i], cam, background.to(device)).image.clamp(0.0, 1.0).cpu()
        render_time += time.perf_counter() - t0
        target = composite_target(frame.image, frame.mask, background)
        rows = {"full": image_metrics(pred, target, lpips)}
        for region, mask in (("hand", frame.hand_mask), ("face", frame.face_mask)):
            if mask is not None:
                rows[region] = image_metrics(pred, target, lpips, mask)
        per_frame[i] = {k: v for k, v in rows.items() if v}
    regions = {}
    for region in REGIONS:
        vals = [r[region] for r in per_frame.values() if region in r]
        if vals:
            regions[region] = RegionMetrics(
                **{k: sum(v[k] for v in vals) / len(vals) for k in ("psnr", "ssim", "lpips")},
                frames=len(vals),
            )
    return EvalResult(
        split=split,
        num_frames=len(indices),
        regions=regions,
        num_gaussians=len(avatar.gaussians),
        render_fps=len(indices) / max(render_time, 1e-9),
        train_seconds=train_seconds,
        per_frame=per_frame,
    )


def metrics_table(results: dict[str, EvalResult]) -> str:
    """A markdown table in the layout of the paper's Table 1 (method, N-GS, PSNR/SSIM/LPIPS x1000
    for full, hand and face; plus training time and render FPS)."""
    head = "| Method | N-GS | " + " | ".join(
        f"{r.capitalize()} PSNR↑ | {r.capitalize()} SSIM↑ | {r.capitalize()} LPIPS↓ (×1000)" for r in REGIONS
    )
    lines = [head + " | Train (s) | FPS |", "|---|---:|" + "---:|" * (3 * len(REGIONS)) + "---:|---:|"]
    for name, res in results.items():
        cells = [name, f"{res.num_gaussians:,}"]
        for region in REGIONS:
            m = res.regions.get(region)
            cells += [f"{m.psnr:.2f}", f"{m.ssim:.4f}", f"{1000 * m.lpips:.2f}"] if m else ["–"] * 3
        cells += [
            f"{res.train_seconds:.0f}" if res.train_seconds is not None else "–",
            f"{res.render_fps:.1f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
