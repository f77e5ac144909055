"""Avatar evaluation as in the paper's Table 1: PSNR / SSIM / LPIPS on the full image and on the
hand and face regions of novel-pose test frames, plus Gaussian count, training time, render FPS.

Protocol (documented choices, ``docs/evaluation.md``):

- target = the test frame's person composited on the render background (the avatar models the
  person, not the scene); prediction = the avatar rendered with the frame's body parameters and
  camera (``dataset.params``; ``dataset.gt_params`` when a dataset has only ground truth).
- full: the metrics on the whole image.
- regions: each of the frame's region masks (``hand_left``, ``hand_right``, ``face``) is cropped
  to its own box: the bounding box of its pixels (coverage > 0.5), grown by ``pad`` pixels on
  every side, then to at least ``min_crop`` pixels per side (kept inside the image), so LPIPS and
  SSIM are defined on small hands. A frame's hand score is the mean over the hands present in it
  (each hand on its own crop, never one box around both); region means run over the frames that
  show the region, and a region no test frame shows is absent.
- poses: by default the test frames' fitted poses (the main protocol: what a user driving the
  avatar with the same alignment gets). With ``PoseRefinement`` the test frames' poses are first
  refined against the test images with the avatar frozen (``train.pose_correction.refine_poses``):
  a second protocol, common in the literature, that separates the avatar's quality from the
  alignment's. ``EvalResult.protocol`` says which; tables must never mix the two.
- metrics: PSNR, SSIM (Gaussian window 11), LPIPS v0.1 with VGG-16 (``lpips_vgg``, the headline:
  the network the EVA authors evaluate with, and one our training loss never sees) and with
  AlexNet (``lpips_alex``, the network our LPIPS loss trains on). Stored as is; tables print
  LPIPS x1000 like the paper.
- placement: ``silhouette_iou``, the intersection over union of the render's alpha and the
  person mask (both > 0.5) in the same crop. Not a quality metric: it tells whether a poor
  region score comes from where the avatar is drawn (the test pose) or from how it looks.
- silhouette errors, on the full image (``debris_and_holes``): ``debris``, the share of the
  render's alpha that falls outside the person mask widened by ``DEBRIS_WIDEN_PX`` (spikes,
  smears and floaters a new pose or view reveals), and ``holes``, the share of the person mask
  the render covers with alpha < 0.5.
- extra regions: a caller with more region masks (e.g. the novel-pose benchmark's arms,
  ``extra_regions``) gets them scored like the hands, each on its own crop.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from eva_engine.avatar import Avatar, Camera
from eva_engine.body import BodyParams
from eva_engine.data.dataset import DatasetLike
from eva_engine.data.resampled import ResampledDataset
from eva_engine.metrics import LPIPS, crop_box, mask_bbox, psnr, ssim
from eva_engine.train.losses import composite_target
from eva_engine.train.pose_correction import PoseCorrectionConfig, refine_poses
from eva_engine.train.trainer import load_training_frames

REGIONS = ("full", "hand", "face")
METRICS = ("psnr", "ssim", "lpips_vgg", "lpips_alex")
PLACEMENT = "silhouette_iou"
REGION_OF_MASK = {"hand_left": "hand", "hand_right": "hand", "face": "face"}
EXTRA_REGION_OF_MASK = {"arm_left": "arm", "arm_right": "arm"}
"""Region masks a caller may add (``extra_regions``) and the region they are scored as."""
DEBRIS_WIDEN_PX = 2
PAD = 4
MIN_CROP = 32
SMALL_REGION_PX = 32
"""A region whose median box is smaller than this (longer side, before growing) is flagged."""
FITTED_POSES = "fitted poses"


@dataclass(frozen=True)
class PoseRefinement:
    """Test-time pose refinement (the second protocol): ``steps`` Adam steps per frame on its
    pose residuals (``PoseCorrectionConfig``'s groups, prior and ``lr``), avatar frozen, L1 + mask
    loss on the test image resampled by ``image_scale`` (metrics are still at full size)."""

    steps: int = 20
    image_scale: float = 0.5
    lr: float = 4e-3

    def __post_init__(self) -> None:
        if self.steps < 1 or not 0 < self.image_scale <= 1 or self.lr <= 0:
            raise ValueError("PoseRefinement needs steps >= 1, 0 < image_scale <= 1 and lr > 0")

    @property
    def protocol(self) -> str:
        return f"test-time refined poses ({self.steps} steps at {self.image_scale:g}x, avatar frozen)"


class ImageMetrics:
    """PSNR, SSIM and both LPIPS networks on one image pair; holds the LPIPS modules (build once).
    With ``vgg=False`` no ``lpips_vgg``: VGG-16 is by far the costlier network, and a job's
    training-frame metrics do without it (``bench/results/quality_cost.md``).

    ``metrics(pred, target)`` with [H, W, 3] images in [0, 1] -> {metric: float}; with
    ``mask [H, W]`` the pair is first cropped to the mask's box (module docstring); with the
    render's ``pred_alpha [H, W]`` and the target's ``person_mask [H, W]`` it adds
    ``silhouette_iou`` on the same crop.
    """

    def __init__(
        self, pad: int = PAD, min_crop: int = MIN_CROP, lpips_alex: LPIPS | None = None, vgg: bool = True
    ) -> None:
        self.pad, self.min_crop = pad, min_crop
        self.lpips_alex = lpips_alex or LPIPS("alex")
        self.lpips_vgg = LPIPS("vgg") if vgg else None

    def box(self, mask: Tensor) -> tuple[int, int, int, int]:
        """The crop box ``(x0, y0, x1, y1)`` of a region mask [H, W] (module docstring)."""
        return crop_box(mask[None, None] > 0.5, pad=self.pad, min_size=self.min_crop)

    @torch.no_grad()
    def __call__(
        self,
        pred: Tensor,
        target: Tensor,
        mask: Tensor | None = None,
        pred_alpha: Tensor | None = None,
        person_mask: Tensor | None = None,
    ) -> dict[str, float]:
        a, b = pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]
        x0, y0, x1, y1 = self.box(mask) if mask is not None else (0, 0, pred.shape[1], pred.shape[0])
        a, b = a[..., y0:y1, x0:x1], b[..., y0:y1, x0:x1]
        out = {"psnr": float(psnr(a, b)[0]), "ssim": float(ssim(a, b)[0])}
        if self.lpips_vgg is not None:
            out["lpips_vgg"] = float(self.lpips_vgg(a, b)[0])
        out["lpips_alex"] = float(self.lpips_alex(a, b)[0])
        if pred_alpha is not None and person_mask is not None:
            out[PLACEMENT] = silhouette_iou(pred_alpha[y0:y1, x0:x1], person_mask[y0:y1, x0:x1])
        return out


def debris_and_holes(alpha: Tensor, mask: Tensor, widen: int = DEBRIS_WIDEN_PX) -> tuple[float, float]:
    """(debris, holes) of a render's ``alpha [H, W]`` against the true person ``mask [H, W]``
    (module docstring): debris = alpha mass outside the mask (> 0.5) widened by ``widen`` pixels
    over all the alpha mass (0 when the render is empty); holes = the mask's pixels with alpha
    < 0.5 over the mask's pixels (0 when the mask is empty)."""
    person = (mask > 0.5).float()[None, None]
    near = torch.nn.functional.max_pool2d(person, 2 * widen + 1, stride=1, padding=widen)[0, 0] > 0
    alpha = alpha.float().clamp(0.0, 1.0)
    total = float(alpha.sum())
    debris = float(alpha[~near].sum()) / total if total > 0 else 0.0
    inside = person[0, 0] > 0
    n = int(inside.sum())
    holes = float((alpha[inside] < 0.5).sum()) / n if n else 0.0
    return debris, holes


def silhouette_iou(alpha: Tensor, mask: Tensor) -> float:
    """Intersection over union of two coverages [H, W] thresholded at 0.5 (1 when both are empty)."""
    p, q = alpha > 0.5, mask > 0.5
    union = int((p | q).sum())
    return float((p & q).sum()) / union if union else 1.0


@dataclass
class RegionMetrics:
    """Means over the frames that show the region. frames: frames scored; crops: crops scored
    (a frame with both hands gives two hand crops); box_px: median longer side of the region's
    box (before growing to ``MIN_CROP``); silhouette_iou: the placement diagnostic (module
    docstring), absent where it was not measured; debris, holes: the silhouette errors (the full
    image only); lpips_vgg: None when scored without VGG (``ImageMetrics(vgg=False)``)."""

    psnr: float
    ssim: float
    lpips_vgg: float | None
    lpips_alex: float
    frames: int
    crops: int = 0
    box_px: float = 0.0
    silhouette_iou: float | None = None
    debris: float | None = None
    holes: float | None = None


@dataclass
class EvalResult:
    """One avatar on one split. regions: "full", "hand", "face" (and "arm" with the arm masks)
    -> metrics (a region no frame shows is absent); per_frame: frame index -> region ("full",
    "hand", "face" and each of ``REGION_MASKS``) -> {metric: value}; notes: warnings a reader of
    the numbers needs."""

    split: str
    num_frames: int
    regions: dict[str, RegionMetrics]
    num_gaussians: int
    render_fps: float
    train_seconds: float | None = None
    per_frame: dict[int, dict[str, dict[str, float]]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    protocol: str = FITTED_POSES
    refined_params: BodyParams | None = field(default=None, repr=False)
    """With ``PoseRefinement``: every frame's params, the scored frames' rows refined."""

    def placement(self, region: str) -> dict[str, float] | None:
        """How far ``region``'s ("full", "hand" or "face") LPIPS-VGG goes with placement, over its
        crops: the mean and median ``silhouette_iou``, the mean LPIPS-VGG of the crops at or above
        the median IoU and of those below, and the rank correlation of IoU and LPIPS-VGG (None
        with fewer than 4 crops or without the IoU)."""
        of_mask = {**REGION_OF_MASK, **EXTRA_REGION_OF_MASK}
        names = [n for n, r in of_mask.items() if r == region] if region != "full" else ["full"]
        rows = [f[n] for f in self.per_frame.values() for n in names if n in f and PLACEMENT in f[n]]
        if len(rows) < 4 or any("lpips_vgg" not in r for r in rows):
            return None
        iou = torch.tensor([r[PLACEMENT] for r in rows], dtype=torch.float64)
        lp = torch.tensor([r["lpips_vgg"] for r in rows], dtype=torch.float64)
        median = float(iou.median())
        above = iou >= median
        ranks = [x.argsort().argsort().double() for x in (iou, lp)]
        rho = torch.corrcoef(torch.stack(ranks))[0, 1]
        return {
            "crops": len(rows),
            "iou_mean": float(iou.mean()),
            "iou_median": median,
            "lpips_vgg_iou_above": float(lp[above].mean()),
            "lpips_vgg_iou_below": float(lp[~above].mean()) if bool((~above).any()) else float("nan"),
            "rank_correlation": float(rho) if torch.isfinite(rho) else 0.0,
        }

    def to_dict(self) -> dict:
        d = dataclasses.asdict(dataclasses.replace(self, refined_params=None))
        d.pop("refined_params")
        d["per_frame"] = {str(k): v for k, v in self.per_frame.items()}
        return d


def _mean(rows: list[dict[str, float]]) -> dict[str, float]:
    """The mean of each key every row has."""
    return {k: sum(r[k] for r in rows) / len(rows) for k in rows[0] if all(k in r for r in rows)}


def box_side(mask: Tensor) -> int:
    """The longer side, in pixels, of a region mask's [H, W] bounding box (before the box rule)."""
    x0, y0, x1, y1 = (int(v) for v in mask_bbox(mask[None, None])[0])
    return max(x1 - x0, y1 - y0)


def _eval_params(dataset: DatasetLike) -> BodyParams:
    params = dataset.params if dataset.params is not None else dataset.gt_params
    if params is None:
        raise ValueError("the dataset has no body parameters to drive the avatar (params or ground truth)")
    return params


@torch.no_grad()
def evaluate_avatar(
    avatar: Avatar,
    dataset: DatasetLike,
    split: str = "test_pose",
    metrics: ImageMetrics | None = None,
    background: Tensor | None = None,
    train_seconds: float | None = None,
    refinement: PoseRefinement | None = None,
    extra_regions: Mapping[int, Mapping[str, Tensor]] | None = None,
    every: int = 1,
) -> EvalResult:
    """Evaluate ``avatar`` on ``dataset.splits[split]`` (see the module docstring).
    extra_regions: frame index -> {``EXTRA_REGION_OF_MASK`` name: [H, W] coverage}; every: score
    every k-th frame of the split only (its first, then every k-th)."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    indices = list(dataset.splits.get(split, []))[::every]
    if not indices:
        raise ValueError(f"the dataset has no frames in split {split!r}")
    params = _eval_params(dataset)
    metrics = metrics or ImageMetrics()
    if background is None:
        bg = dataset.meta.background
        background = torch.tensor(bg if bg is not None else (1.0, 1.0, 1.0), dtype=torch.float32)
    avatar.eval()
    device = avatar.shape.device
    if refinement is not None:
        with torch.enable_grad():
            params = refined_params(avatar, dataset, indices, params, background, refinement)
    per_frame: dict[int, dict[str, dict[str, float]]] = {}
    boxes: dict[str, list[int]] = {}
    render_time = 0.0
    for i in indices:
        frame = dataset[i]
        h, w = frame.image.shape[:2]
        cam = Camera(frame.K.float(), frame.viewmat.float(), w, h)
        t0 = time.perf_counter()
        render = avatar(params[i], cam, background.to(device))
        pred = render.image.clamp(0.0, 1.0).cpu()
        render_time += time.perf_counter() - t0
        alpha = render.alpha.reshape(h, w).cpu()
        target = composite_target(frame.image, frame.mask, background)
        rows: dict[str, dict[str, float]] = {"full": metrics(pred, target, None, alpha, frame.mask)}
        rows["full"]["debris"], rows["full"]["holes"] = debris_and_holes(alpha, frame.mask)
        crops: dict[str, list[dict[str, float]]] = {}
        masks = {**frame.regions, **(extra_regions or {}).get(i, {})}
        for name, region in {**REGION_OF_MASK, **EXTRA_REGION_OF_MASK}.items():
            mask = masks.get(name)
            if mask is None or not bool((mask > 0.5).any()):
                continue
            rows[name] = metrics(pred, target, mask, alpha, frame.mask)
            crops.setdefault(region, []).append(rows[name])
            boxes.setdefault(region, []).append(box_side(mask))
        rows.update({region: _mean(found) for region, found in crops.items() if found})
        per_frame[i] = rows
    regions = {}
    of_mask = {**REGION_OF_MASK, **EXTRA_REGION_OF_MASK}
    for region in (*REGIONS, *dict.fromkeys(EXTRA_REGION_OF_MASK.values())):
        found = [r[region] for r in per_frame.values() if region in r]
        if not found:
            continue
        n_crops = sum(
            1 for r in per_frame.values() for name, reg in of_mask.items() if reg == region and name in r
        )
        regions[region] = RegionMetrics(
            **{"lpips_vgg": None, **_mean(found)},
            frames=len(found),
            crops=n_crops if region != "full" else len(found),
            box_px=float(statistics.median(boxes[region])) if region in boxes else float(max(h, w)),
        )
    notes = [
        f"{region} regions are small (median box {m.box_px:.0f} px < {SMALL_REGION_PX} px): "
        f"their metrics see little detail at this resolution"
        for region, m in regions.items()
        if region != "full" and m.box_px < SMALL_REGION_PX
    ]
    return EvalResult(
        split=split,
        num_frames=len(indices),
        regions=regions,
        num_gaussians=len(avatar.gaussians),
        render_fps=len(indices) / max(render_time, 1e-9),
        train_seconds=train_seconds,
        per_frame=per_frame,
        notes=notes,
        protocol=refinement.protocol if refinement is not None else FITTED_POSES,
        refined_params=params if refinement is not None else None,
    )


def refined_params(
    avatar: Avatar,
    dataset: DatasetLike,
    indices: list[int],
    params: BodyParams,
    background: Tensor,
    refinement: PoseRefinement,
) -> BodyParams:
    """``params`` (all frames) with the rows ``indices`` refined against their images, the avatar
    frozen (``PoseRefinement``); the other rows unchanged."""
    device = avatar.shape.device
    frames = load_training_frames(ResampledDataset(dataset, refinement.image_scale), indices)
    targets = torch.stack(
        [composite_target(img, m, background) for img, m in zip(frames.images, frames.masks, strict=True)]
    )
    config = PoseCorrectionConfig(enabled=True, start_iter=0, lr=refinement.lr)
    rows = params[torch.tensor(indices)].map(lambda t: t.to(device))
    fixed, _ = refine_poses(
        avatar,
        targets.to(device),
        frames.masks.to(device),
        frames.cameras,
        rows,
        background.to(device),
        config,
        refinement.steps,
    )
    out = params.map(lambda t: t.detach().clone())
    for k, v in fixed.tensors().items():
        getattr(out, k)[torch.tensor(indices)] = v.to(getattr(out, k))
    return out


def metrics_table(results: dict[str, EvalResult]) -> str:
    """A markdown table in the layout of the paper's Table 1: method, N-GS, then PSNR / SSIM /
    LPIPS-VGG ×1000 / LPIPS-Alex ×1000 for full, hand and face; the silhouette errors (debris
    and holes, % of the full image's: ``debris_and_holes``), training time and render FPS."""
    cols = ("PSNR↑", "SSIM↑", "LPIPS-VGG↓", "LPIPS-Alex↓")
    head = "| Method | N-GS | " + " | ".join(f"{r.capitalize()} {c}" for r in REGIONS for c in cols)
    lines = [
        head + " | Debris %↓ | Holes %↓ | Train (s) | FPS |",
        "|---|---:|" + "---:|" * (len(cols) * len(REGIONS)) + "---:|---:|---:|---:|",
    ]
    for name, res in results.items():
        cells = [name, f"{res.num_gaussians:,}"]
        for region in REGIONS:
            m = res.regions.get(region)
            cells += (
                [f"{m.psnr:.2f}", f"{m.ssim:.4f}", f"{1000 * m.lpips_vgg:.2f}", f"{1000 * m.lpips_alex:.2f}"]
                if m
                else ["–"] * len(cols)
            )
        full = res.regions.get("full")
        cells += (
            [f"{100 * v:.2f}" if v is not None else "–" for v in (full.debris, full.holes)]
            if full
            else ["–"] * 2
        )
        cells += [
            f"{res.train_seconds:.0f}" if res.train_seconds is not None else "–",
            f"{res.render_fps:.1f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(
        "LPIPS ×1000. LPIPS-VGG is held out (no method trains on it); the LPIPS loss trains on AlexNet."
    )
    protocols = sorted({res.protocol for res in results.values()})
    if len(protocols) > 1:
        raise ValueError(f"one table, one protocol: got {protocols}")
    lines.append(f"Poses: {protocols[0]}." if protocols else "")
    for name, res in results.items():
        counts = ", ".join(
            f"{r} {m.frames} frames / {m.crops} crops" for r, m in res.regions.items() if r != "full"
        )
        lines.append(f"{name}: {res.num_frames} test frames; regions scored: {counts or 'none'}.")
        lines += [f"{name}: note: {n}" for n in res.notes]
    return "\n".join(lines) + "\n"
