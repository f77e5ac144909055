"""An avatar's quality report: how it does on frames it never trained on, and what the pipeline
saw of the person (issue 41's ``quality`` in ``avatar.json``).

The scores come from the held-out frames of the dataset (preprocessing puts every k-th kept frame
in ``test_pose``; the job path always keeps some out), rendered with their fitted poses, so they
say what a user will see in new poses, unlike the fit on training frames (``metrics``). The
detection summary comes from what preprocessing recorded in the dataset's ``meta.json``.

The verdict (``good`` / ``fair`` / ``poor``, :func:`verdict`) reads the held-out LPIPS-VGG
against thresholds calibrated on the hard-input benchmark (``bench/hard_inputs.py``, where each
avatar is also scored against the truth; ``docs/quality.md``), and lowers ``good`` to ``fair``
for what the pipeline saw that is known to cost quality (hands or face seldom found, small
hands, a large fit error, many frames dropped). Each reason is a sentence for the user.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict

from eva_engine.eval.evaluate import ImageMetrics, evaluate_avatar

HELD_OUT_SPLIT = "test_pose"
HELD_OUT_EVERY = 10
MIN_HELD_OUT = 4


def held_out_every(frames: int) -> int:
    """``test_every`` that keeps about one frame in ``HELD_OUT_EVERY`` out of training, and at
    least ``MIN_HELD_OUT`` when the clip has twice that (a shorter clip keeps a half to a third out; 2
    frames keep 1, 1 frame keeps none, as ``PreprocessConfig.test_every`` places them)."""
    if frames < 2:
        return 0
    if frames < 2 * MIN_HELD_OUT:
        return 2 if frames < 6 else 3
    return max(2, min(HELD_OUT_EVERY, frames // MIN_HELD_OUT))


def _finite(value: float | None) -> float | None:
    """JSON has no inf or NaN: an identical crop's PSNR (inf) or an unmeasured value is None."""
    return value if value is not None and math.isfinite(value) else None


class HeldOutScores(BaseModel):
    """The avatar on its held-out frames, full image: PSNR (dB), SSIM, LPIPS-VGG and -Alex (x1000
    not applied: 0-1), the silhouette's IoU with the person mask in the crop, and the debris
    (alpha outside the person) and holes (person without alpha) shares; face and hand LPIPS-VGG
    where frames show them. None: not measurable (e.g. a perfect crop's PSNR)."""

    model_config = ConfigDict(extra="ignore")  # a newer writer's keys

    split: str
    frames: int
    psnr: float | None
    ssim: float | None
    lpips_vgg: float | None
    lpips_alex: float | None
    silhouette_iou: float | None = None
    debris: float | None = None
    holes: float | None = None
    face_lpips_vgg: float | None = None
    hand_lpips_vgg: float | None = None
    hand_px: float | None = None
    """The hands' median box side in the held-out frames that show them (pixels)."""


class DetectionSummary(BaseModel):
    """What preprocessing saw: frames decoded / kept / dropped (no person found), the share of
    decoded frames with each part found, the fit's mean 2D error per group (pixels), and the
    person's median height in the kept frames (pixels and share of the frame's height)."""

    model_config = ConfigDict(extra="ignore")  # a newer writer's keys

    frames_decoded: int | None = None
    frames_kept: int | None = None
    frames_dropped: int | None = None
    found: dict[str, float] = {}
    reprojection_px: dict[str, float | None] = {}
    person_height_px: float | None = None
    person_height_share: float | None = None


Verdict = Literal["good", "fair", "poor"]


class QualityReport(BaseModel):
    """``avatar.json``'s ``quality``: the ``verdict`` with its ``reasons`` (None: nothing to judge
    by, no held-out frame), ``held_out`` (None: the dataset kept no frame out) and ``detection``
    (None: the dataset did not come from ``preprocess_video``)."""

    model_config = ConfigDict(extra="ignore")  # a newer writer's keys

    verdict: Verdict | None = None
    reasons: list[str] = []
    held_out: HeldOutScores | None = None
    detection: DetectionSummary | None = None


@dataclass(frozen=True)
class VerdictRules:
    """Thresholds of :func:`verdict`. poor_lpips / fair_lpips: held-out LPIPS-VGG (0-1, full
    image) above which an avatar is poor / at best fair (set on ``bench/hard_inputs.py``:
    ``docs/quality.md``); the
    rest lower good to fair: a hand or the face found in fewer than ``min_found`` of the frames,
    hands under ``min_hand_px``, the body's or hands' fit error over ``max_fit_px`` /
    ``max_hand_fit_px``, more than ``max_dropped`` of the frames dropped."""

    poor_lpips: float = 0.155
    fair_lpips: float = 0.10
    min_found: float = 0.5
    min_hand_px: float = 20.0
    max_fit_px: float = 15.0
    max_hand_fit_px: float = 15.0
    max_dropped: float = 0.2


def verdict(
    held_out: HeldOutScores | None, detection: DetectionSummary | None, rules: VerdictRules | None = None
) -> tuple[Verdict | None, list[str]]:
    """The verdict and its reasons (module docstring); (None, []) without held-out scores."""
    rules = rules or VerdictRules()
    if held_out is None or held_out.lpips_vgg is None:
        return None, []
    lpips = held_out.lpips_vgg
    reasons: list[str] = []
    if lpips > rules.poor_lpips:
        level: Verdict = "poor"
        reasons.append(
            f"on frames it never trained on, the avatar's renders are far from the video "
            f"(LPIPS-VGG {lpips:.3f}; poor above {rules.poor_lpips:.2f})"
        )
    elif lpips > rules.fair_lpips:
        level = "fair"
        reasons.append(
            f"on frames it never trained on, the avatar's renders are off from the video "
            f"(LPIPS-VGG {lpips:.3f}; good up to {rules.fair_lpips:.2f})"
        )
    else:
        level = "good"
    cautions = []
    if detection is not None:
        names = {"left_hand": "the left hand", "right_hand": "the right hand", "face": "the face"}
        for key, name in names.items():
            share = detection.found.get(key)
            if share is not None and share < rules.min_found:
                cautions.append(f"{name} was found in only {100 * share:.0f}% of the frames")
        fit = detection.reprojection_px
        if (fit.get("body") or 0.0) > rules.max_fit_px:
            cautions.append(f"the body's fit is off by {fit['body']:.0f} px on average")
        if (fit.get("hands") or 0.0) > rules.max_hand_fit_px:
            cautions.append(f"the hands' fit is off by {fit['hands']:.0f} px on average")
        decoded, dropped = detection.frames_decoded, detection.frames_dropped
        if decoded and dropped is not None and dropped > rules.max_dropped * decoded:
            cautions.append(f"no person was found in {dropped} of {decoded} frames")
    if held_out.hand_px is not None and held_out.hand_px < rules.min_hand_px:
        cautions.append(
            f"the hands are under {rules.min_hand_px:.0f} px ({held_out.hand_px:.0f} px): little detail"
        )
    if cautions and level == "good":
        level = "fair"
    return level, reasons + cautions


def held_out_scores(avatar, dataset, metrics: ImageMetrics | None = None) -> HeldOutScores | None:
    """Scores of ``avatar`` on ``dataset``'s held-out split, or None when it has no such frame."""
    if not dataset.splits.get(HELD_OUT_SPLIT):
        return None
    result = evaluate_avatar(avatar, dataset, split=HELD_OUT_SPLIT, metrics=metrics)
    full = result.regions.get("full")
    if full is None:
        return None
    region = {name: _finite(r.lpips_vgg) for name, r in result.regions.items()}
    return HeldOutScores(
        split=HELD_OUT_SPLIT,
        frames=result.num_frames,
        psnr=_finite(full.psnr),
        ssim=_finite(full.ssim),
        lpips_vgg=_finite(full.lpips_vgg),
        lpips_alex=_finite(full.lpips_alex),
        silhouette_iou=_finite(full.silhouette_iou),
        debris=_finite(full.debris),
        holes=_finite(full.holes),
        face_lpips_vgg=region.get("face"),
        hand_lpips_vgg=region.get("hand"),
        hand_px=result.regions["hand"].box_px if "hand" in result.regions else None,
    )


def detection_summary(dataset) -> DetectionSummary | None:
    """What ``preprocess_video`` recorded in the dataset, and the person masks' heights; None for
    a dataset it did not write (synthetic, or converted from elsewhere)."""
    extra: dict[str, Any] = dataset.meta.extra or {}
    if "detection_rates" not in extra:
        return None
    frames = extra.get("frames", {})
    fitted = extra.get("reprojection_px", {}).get("fitted", {})
    from eva_engine.align.input_checks import person_height

    heights = []
    for i in range(len(dataset)):
        mask = dataset.mask(i) if hasattr(dataset, "mask") else dataset[i].mask  # [H, W]
        if (h := person_height(mask.numpy())) is not None:
            heights.append(h)
    height = float(torch.tensor(heights).median()) if heights else None
    image_h = dataset.meta.image_size[0]
    return DetectionSummary(
        frames_decoded=frames.get("decoded"),
        frames_kept=frames.get("kept"),
        frames_dropped=frames.get("dropped"),
        found={k: float(v) for k, v in extra["detection_rates"].items()},
        reprojection_px={k: _finite(v) for k, v in fitted.items()},
        person_height_px=height,
        person_height_share=height / image_h if height is not None and image_h else None,
    )


def quality_report(
    avatar, dataset, metrics: ImageMetrics | None = None, rules: VerdictRules | None = None
) -> QualityReport:
    """The quality report of ``avatar`` trained on ``dataset`` (module docstring)."""
    held_out = held_out_scores(avatar, dataset, metrics)
    detection = detection_summary(dataset)
    level, reasons = verdict(held_out, detection, rules)
    return QualityReport(verdict=level, reasons=reasons, held_out=held_out, detection=detection)
