"""Evaluation: per-hand region crops from the dataset's masks, both LPIPS networks, the paper's
table layout, clear errors."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from helpers.scenes import SceneDataset, teacher_scene

from eva_engine.avatar import Avatar, AvatarConfig, Camera
from eva_engine.eval import METRICS, EvalResult, ImageMetrics, RegionMetrics, evaluate_avatar, metrics_table
from eva_engine.eval.evaluate import MIN_CROP, PAD


@pytest.fixture(scope="module")
def metrics():
    return ImageMetrics()


def test_the_teacher_beats_an_untrained_avatar(anny_model, metrics):
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=48)
    cfg = AvatarConfig(init_max_gaussians=800, mlp_width=8, pe_frequencies=1, sh_degree=0)
    fresh = Avatar.create(anny_model, anny_model.shape_defaults, cfg)
    good = evaluate_avatar(teacher, ds, metrics=metrics, train_seconds=1.0)
    bad = evaluate_avatar(fresh, ds, metrics=metrics)
    assert (
        good.split == "test_pose" and good.num_frames == 1 and set(good.regions) == {"full", "hand", "face"}
    )
    for region in ("full", "hand", "face"):
        g, b = good.regions[region], bad.regions[region]
        assert (
            g.psnr > b.psnr + 5
            and g.ssim > b.ssim
            and g.lpips_vgg < b.lpips_vgg
            and g.lpips_alex < b.lpips_alex
        )
    # both hands are in the frame: two hand crops, one frame
    assert good.regions["hand"].crops == 2 and good.regions["hand"].frames == 1
    frame = good.per_frame[2]
    assert {"hand_left", "hand_right", "face", "hand", "full"} <= set(frame)
    for m in METRICS:  # the frame's hand score is the mean of its two hands
        assert frame["hand"][m] == pytest.approx((frame["hand_left"][m] + frame["hand_right"][m]) / 2)
    # The teacher is drawn where its own masks are: its silhouette matches in every region.
    for region in ("full", "hand", "face"):
        assert good.regions[region].silhouette_iou > 0.9, region
    assert good.regions["full"].silhouette_iou > bad.regions["full"].silhouette_iou
    assert good.num_gaussians == len(teacher.gaussians) and good.render_fps > 0
    assert set(good.to_dict()["per_frame"]) == {"2"}
    with pytest.raises(ValueError, match="no frames"):
        evaluate_avatar(teacher, ds, split="test_view", metrics=metrics)


def test_metrics_without_vgg_score_the_rest_the_same(anny_model, metrics):
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=48)
    both = evaluate_avatar(teacher, ds, metrics=metrics)
    light = evaluate_avatar(teacher, ds, metrics=ImageMetrics(lpips_alex=metrics.lpips_alex, vgg=False))
    assert set(light.regions) == set(both.regions)
    for region, scores in light.regions.items():
        assert scores.lpips_vgg is None and both.regions[region].lpips_vgg is not None
        same = dataclasses.replace(both.regions[region], lpips_vgg=None)
        assert scores == same
    assert "lpips_vgg" not in light.per_frame[2]["full"]


def test_region_metrics_crop_to_the_region(metrics):
    torch.manual_seed(0)
    target = torch.rand(64, 64, 3)
    pred = target.clone()
    pred[:, 40:] = 0.0  # wrong only on the right
    mask = torch.zeros(64, 64)
    mask[5:10, 5:10] = 1.0  # a small region on the left: grown to 32 px, still exact there
    m = metrics(pred, target, mask)
    assert m["psnr"] == float("inf") and m["lpips_vgg"] == 0.0 and m["lpips_alex"] == 0.0
    assert metrics(pred, target)["psnr"] < 20


def test_silhouette_iou_measures_placement_in_the_crop(metrics):
    target = torch.ones(64, 64, 3)
    person = torch.zeros(64, 64)
    person[10:30, 10:30] = 1.0  # 20 x 20
    alpha = torch.zeros(64, 64)
    alpha[10:30, 20:40] = 1.0  # the same square 10 px to the right: 200 of 600 pixels shared
    assert metrics(target, target, None, alpha, person)["silhouette_iou"] == pytest.approx(200 / 600)
    region = torch.zeros(64, 64)
    region[54:60, 54:60] = 1.0  # grown to a 32 px crop in the corner: neither silhouette there
    assert metrics(target, target, region, alpha, person)["silhouette_iou"] == 1.0
    assert "silhouette_iou" not in metrics(target, target, region)


def test_each_hand_is_scored_on_its_own_crop(anny_model, metrics):
    """Hands far apart: each hand's crop holds only its own hand. An error painted on the right
    hand changes only the right hand's score, and a frame whose left hand is absent is scored on
    the right hand alone."""
    size = 192
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=size, amplitude=0.0)
    f = ds[2]
    left, right = f.regions["hand_left"], f.regions["hand_right"]
    for own, other in ((left, right), (right, left)):
        x0, y0, x1, y1 = metrics.box(own)
        assert x1 - x0 >= MIN_CROP and y1 - y0 >= MIN_CROP
        assert float(own[y0:y1, x0:x1].sum()) == float(own.sum())  # the whole hand ...
        assert float(other[y0:y1, x0:x1].sum()) == 0.0  # ... and nothing of the other one
        ys, xs = torch.nonzero(own > 0.5, as_tuple=True)
        assert x1 - x0 <= max(MIN_CROP, int(xs.max() - xs.min()) + 1 + 2 * PAD)
    # the avatar's own render is the target, with the right hand painted black
    with torch.no_grad():
        cam = Camera(f.K, f.viewmat, size, size)
        target = teacher(ds.params[2], cam, torch.ones(3)).image.clamp(0, 1)
    target[right > 0.5] = 0.0
    frame = dataclasses.replace(f, image=target, mask=torch.ones(size, size), regions=dict(f.regions))
    one = SceneDataset([frame], ds.params[[2]], {"train": [], "test_pose": [0], "test_view": []})
    res = evaluate_avatar(teacher, one, metrics=metrics)
    scores = res.per_frame[0]
    assert scores["hand_left"]["psnr"] > 40 and scores["hand_left"]["lpips_vgg"] < 1e-3  # untouched
    assert scores["hand_right"]["psnr"] < 25 and scores["hand_right"]["lpips_vgg"] > 0.05
    frame.regions["hand_left"] = torch.zeros(size, size)
    res = evaluate_avatar(teacher, one, metrics=metrics)
    assert "hand_left" not in res.per_frame[0] and res.regions["hand"].crops == 1
    assert res.per_frame[0]["hand"] == res.per_frame[0]["hand_right"]


def test_table_in_the_papers_layout():
    r = EvalResult(
        split="test_pose",
        num_frames=4,
        num_gaussians=19458,
        render_fps=12.5,
        train_seconds=300.0,
        regions={
            "full": RegionMetrics(28.88, 0.9609, 0.04493, 0.0321, 4, 4, 512.0, debris=0.0123, holes=0.004),
            "hand": RegionMetrics(25.28, 0.9189, 0.09137, 0.0712, 3, 5, 21.0),
        },
        notes=["hand regions are small"],
    )
    table = metrics_table({"3DGS + body": r})
    lines = table.strip().splitlines()
    assert lines[0].startswith(
        "| Method | N-GS | Full PSNR↑ | Full SSIM↑ | Full LPIPS-VGG↓ | Full LPIPS-Alex↓ |"
    )
    assert lines[2] == (
        "| 3DGS + body | 19,458 | 28.88 | 0.9609 | 44.93 | 32.10 | 25.28 | 0.9189 | 91.37 | 71.20 | "
        "– | – | – | – | 1.23 | 0.40 | 300 | 12.5 |"
    )
    assert "held out" in table and "hand 3 frames / 5 crops" in table and "hand regions are small" in table


def test_test_time_refinement_is_a_separate_protocol(anny_model, metrics):
    """With the test frame's pose off, the refined protocol scores the teacher higher than the
    fitted one, only the test rows move, and one table never mixes the two protocols."""
    from eva_engine.eval import PoseRefinement

    ds, teacher = teacher_scene(anny_model, n_frames=3, size=64)
    off = ds.params.map(lambda t: t.clone())
    off.joints[2, anny_model.pose_joint_names.index("lowerarm01.L"), 2] += 0.3
    off.transl[2, 0] += 0.03
    shifted = SceneDataset(ds.frames, off, ds.splits)
    fitted = evaluate_avatar(teacher, shifted, metrics=metrics)
    refinement = PoseRefinement(steps=40, image_scale=1.0, lr=5e-3)
    refined = evaluate_avatar(teacher, shifted, metrics=metrics, refinement=refinement)
    assert fitted.protocol == "fitted poses" and refined.protocol == refinement.protocol
    assert refined.regions["full"].psnr > fitted.regions["full"].psnr + 2
    assert torch.equal(shifted.params.joints, off.joints)  # the dataset's own params are untouched
    with pytest.raises(ValueError, match="one protocol"):
        metrics_table({"fitted": fitted, "refined": refined})
    with pytest.raises(ValueError):
        PoseRefinement(steps=0)


def test_placement_splits_region_scores_by_silhouette_overlap():
    """Crops drawn where the person is score better: placement reports it per region."""
    per_frame = {}
    for i in range(6):
        iou = 0.5 + 0.08 * i
        row = {"lpips_vgg": 0.4 - 0.05 * i, "silhouette_iou": iou}
        per_frame[i] = {"hand_left": row, "hand_right": dict(row), "face": {"lpips_vgg": 0.1, "psnr": 20.0}}
    r = EvalResult(split="test_pose", num_frames=6, regions={}, num_gaussians=1, render_fps=1.0)
    r.per_frame = per_frame
    p = r.placement("hand")
    assert p["crops"] == 12 and p["rank_correlation"] == pytest.approx(-1.0, abs=0.05)
    assert p["lpips_vgg_iou_above"] < p["lpips_vgg_iou_below"]
    assert p["iou_mean"] == pytest.approx(0.7)
    assert r.placement("face") is None  # no IoU measured
    assert r.placement("full") is None


def test_debris_and_holes_on_hand_made_masks():
    """Debris: alpha mass outside the person widened by 2 px, over all alpha; holes: the person's
    pixels left below alpha 0.5. Exact on hand-made masks."""
    from eva_engine.eval.evaluate import debris_and_holes

    mask = torch.zeros(40, 40)
    mask[10:30, 10:30] = 1.0  # 400 px
    perfect = mask.clone()
    assert debris_and_holes(perfect, mask) == (0.0, 0.0)
    # A soft fringe within 2 px of the person is not debris.
    fringe = mask.clone()
    fringe[8:10, 10:30] = 0.5
    assert debris_and_holes(fringe, mask)[0] == 0.0
    # A spike 5 px away: 20 px of alpha 1 beyond the widened mask.
    spike = mask.clone()
    spike[35, 10:30] = 1.0
    debris, holes = debris_and_holes(spike, mask)
    assert debris == pytest.approx(20 / 420) and holes == 0.0
    # A hole: 100 of the 400 person pixels at alpha 0.3.
    holed = mask.clone()
    holed[10:20, 10:20] = 0.3
    debris, holes = debris_and_holes(holed, mask)
    assert debris == 0.0 and holes == pytest.approx(100 / 400)
    # Degenerate inputs: an empty render, an empty mask, alpha out of [0, 1].
    assert debris_and_holes(torch.zeros(40, 40), mask) == (0.0, 1.0)
    assert debris_and_holes(perfect, torch.zeros(40, 40)) == (1.0, 0.0)
    assert debris_and_holes(mask * 7.0, mask) == (0.0, 0.0)


def test_evaluation_reports_silhouette_errors_and_extra_regions(anny_model, metrics):
    """Every split scored carries debris and holes on the full image; arm masks given by the
    caller are scored like the hands, each arm on its own crop."""
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=48)
    res = evaluate_avatar(teacher, ds, metrics=metrics)
    full = res.regions["full"]
    assert 0.0 <= full.debris < 0.05 and 0.0 <= full.holes < 0.2
    assert "debris" in res.per_frame[2]["full"] and res.regions["hand"].debris is None
    arm = torch.zeros(48, 48)
    arm[5:20, 5:12] = 1.0
    other = torch.zeros(48, 48)
    other[5:20, 30:40] = 1.0
    extra = {2: {"arm_left": arm, "arm_right": other}}
    with_arms = evaluate_avatar(teacher, ds, metrics=metrics, extra_regions=extra)
    assert with_arms.regions["arm"].crops == 2 and with_arms.regions["arm"].frames == 1
    row = with_arms.per_frame[2]
    assert row["arm"]["lpips_vgg"] == pytest.approx(
        (row["arm_left"]["lpips_vgg"] + row["arm_right"]["lpips_vgg"]) / 2
    )
    assert with_arms.regions["full"].psnr == full.psnr  # the other regions are untouched
