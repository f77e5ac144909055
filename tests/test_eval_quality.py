"""The avatar's quality report: which frames are held out, held-out scores that stay valid JSON
when a score is infinite, the detection summary of a preprocessed dataset, and the verdict with
its reasons."""

from __future__ import annotations

import json

import pytest
import torch
from helpers.scenes import teacher_scene

from eva_engine.eval import ImageMetrics, QualityReport, VerdictRules, held_out_every, quality_report, verdict
from eva_engine.eval.quality import DetectionSummary, HeldOutScores
from eva_engine.metrics import LPIPS


@pytest.mark.parametrize(
    ("frames", "held_out"),
    [(0, 0), (1, 0), (2, 1), (4, 2), (6, 2), (8, 4), (20, 4), (40, 4), (120, 12), (300, 30)],
)
def test_held_out_frames_are_a_tenth_and_at_least_four(frames, held_out):
    every = held_out_every(frames)
    assert every == 0 or every >= 2  # PreprocessConfig's rule
    assert (len(range(every - 1, frames, every)) if every else 0) == held_out


def test_held_out_scores_of_the_teacher_on_its_own_renders(anny_model):
    """The teacher scored on its held-out frames (its own renders, composited as training sees
    them): close, the silhouette exact, and the report a valid JSON document."""
    ds, teacher = teacher_scene(anny_model, n_frames=6, size=48)
    report = quality_report(teacher, ds, ImageMetrics(lpips_alex=LPIPS()))
    held = report.held_out
    assert held is not None and held.split == "test_pose" and held.frames == len(ds.splits["test_pose"]) == 2
    assert held.psnr > 25 and held.lpips_vgg < 0.05 and held.face_lpips_vgg is not None
    assert held.silhouette_iou == pytest.approx(1.0) and held.debris == 0.0 and held.holes == 0.0
    assert report.detection is None  # not a preprocessed video
    # Close to its own renders, but at 48 px its hands are too small to judge: fair, for that reason.
    assert (
        report.verdict == "fair"
        and len(report.reasons) == 1
        and "the hands are under 20 px" in report.reasons[0]
    )
    doc = json.dumps(report.model_dump(), allow_nan=False)
    assert QualityReport.model_validate_json(doc) == report


def test_an_infinite_score_is_null_not_infinity(anny_model, monkeypatch):
    """An identical crop scores PSNR +inf, which JSON cannot hold: the report says None."""
    from eva_engine.eval import quality
    from eva_engine.eval.evaluate import EvalResult, RegionMetrics

    full = RegionMetrics(
        psnr=float("inf"), ssim=1.0, lpips_vgg=0.0, lpips_alex=0.0, frames=2, debris=float("nan")
    )
    result = EvalResult("test_pose", 2, {"full": full}, num_gaussians=1, render_fps=1.0)
    monkeypatch.setattr(quality, "evaluate_avatar", lambda *args, **kwargs: result)
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=32)
    held = quality.held_out_scores(teacher, ds)
    assert held.psnr is None and held.debris is None and held.lpips_vgg == 0.0
    json.dumps(held.model_dump(), allow_nan=False)


def test_no_held_out_frames_no_scores(anny_model):
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=32)
    ds.splits["test_pose"] = []
    assert quality_report(teacher, ds).held_out is None


def test_detection_summary_of_a_preprocessed_dataset(tmp_path):
    """What preprocessing wrote in meta.json, and the masks' median height."""
    from eva_engine.data import DatasetMeta, DatasetWriter, load_dataset
    from eva_engine.eval.quality import detection_summary

    meta = DatasetMeta(source="video", fps=10.0, image_size=(40, 30), name="clip")
    with DatasetWriter(tmp_path / "ds", meta) as writer:
        for top in (5, 10, 15):  # person heights 20, 15, 10 px
            mask = torch.zeros(40, 30)
            mask[top:25, 10:20] = 1.0
            writer.add_frame(torch.rand(40, 30, 3), mask, K=torch.eye(3), viewmat=torch.eye(4), time=0.0)
        writer.finish(
            {"train": [0, 1, 2]},
            extra={
                "frames": {"decoded": 4, "kept": 3, "dropped": 1, "every": 1},
                "detection_rates": {"pose": 0.75, "left_hand": 0.5, "right_hand": 0.25, "face": 0.75},
                "reprojection_px": {"initial": {"body": 9.0}, "fitted": {"body": 3.5, "hands": None}},
            },
        )
    summary = detection_summary(load_dataset(tmp_path / "ds"))
    assert (summary.frames_decoded, summary.frames_kept, summary.frames_dropped) == (4, 3, 1)
    assert summary.found == {"pose": 0.75, "left_hand": 0.5, "right_hand": 0.25, "face": 0.75}
    assert summary.reprojection_px == {"body": 3.5, "hands": None}
    assert summary.person_height_px == 15.0 and summary.person_height_share == pytest.approx(15 / 40)


def _held(lpips: float, hand_px: float | None = 60.0) -> HeldOutScores:
    return HeldOutScores(
        split="test_pose", frames=4, psnr=25.0, ssim=0.9, lpips_vgg=lpips, lpips_alex=0.1, hand_px=hand_px
    )


def _seen(**changes) -> DetectionSummary:
    base = dict(
        frames_decoded=100,
        frames_kept=100,
        frames_dropped=0,
        found={"pose": 1.0, "left_hand": 0.9, "right_hand": 0.9, "face": 1.0},
        reprojection_px={"body": 4.0, "hands": 3.0, "face": 1.0},
    )
    return DetectionSummary(**{**base, **changes})


def test_the_verdict_follows_the_held_out_lpips_bands():
    rules = VerdictRules(poor_lpips=0.2, fair_lpips=0.1)
    assert verdict(_held(0.05), _seen(), rules) == ("good", [])
    level, reasons = verdict(_held(0.15), _seen(), rules)
    assert level == "fair" and "LPIPS-VGG 0.150; good up to 0.10" in reasons[0]
    level, reasons = verdict(_held(0.35), None, rules)
    assert level == "poor" and "poor above 0.20" in reasons[0] and len(reasons) == 1
    assert verdict(None, _seen(), rules) == (None, [])
    assert verdict(_held(float("nan")).model_copy(update={"lpips_vgg": None}), _seen(), rules) == (None, [])


@pytest.mark.parametrize(
    ("held", "seen", "words"),
    [
        (
            _held(0.05),
            _seen(found={"pose": 1.0, "left_hand": 0.3, "right_hand": 0.9, "face": 1.0}),
            "the left hand was found in only 30%",
        ),
        (_held(0.05), _seen(reprojection_px={"body": 22.0, "hands": 3.0}), "the body's fit is off by 22 px"),
        (_held(0.05), _seen(reprojection_px={"body": 2.0, "hands": 31.0}), "the hands' fit is off by 31 px"),
        (_held(0.05), _seen(frames_dropped=40, frames_kept=60), "no person was found in 40 of 100 frames"),
        (_held(0.05, hand_px=12.0), _seen(), "the hands are under 20 px (12 px)"),
    ],
)
def test_what_the_pipeline_saw_lowers_good_to_fair_with_its_reason(held, seen, words):
    level, reasons = verdict(held, seen)
    assert level == "fair" and any(words in r for r in reasons), reasons
    # ... and never raises a poor avatar, nor lowers it further.
    assert verdict(held.model_copy(update={"lpips_vgg": 0.9}), seen)[0] == "poor"


def test_a_report_without_a_verdict_still_reads():
    """An avatar.json written before the verdict existed reads with none."""
    old = {"held_out": None, "detection": None}
    report = QualityReport.model_validate(old)
    assert report.verdict is None and report.reasons == []
