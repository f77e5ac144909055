"""Evaluation: region metrics from the dataset's masks, the paper's table layout, clear errors."""

from __future__ import annotations

import pytest
import torch
from test_avatar_scenes import teacher_scene

from eva_engine.avatar import Avatar, AvatarConfig
from eva_engine.eval import EvalResult, RegionMetrics, evaluate_avatar, image_metrics, metrics_table
from eva_engine.metrics import LPIPS


@pytest.fixture(scope="module")
def lpips():
    return LPIPS()


def test_the_teacher_beats_an_untrained_avatar(anny_model, lpips):
    ds, teacher = teacher_scene(anny_model, n_frames=3, size=48)
    cfg = AvatarConfig(init_max_gaussians=800, mlp_width=8, pe_frequencies=1, sh_degree=0)
    fresh = Avatar.create(anny_model, anny_model.shape_defaults, cfg)
    good = evaluate_avatar(teacher, ds, lpips=lpips, train_seconds=1.0)
    bad = evaluate_avatar(fresh, ds, lpips=lpips)
    assert (
        good.split == "test_pose" and good.num_frames == 1 and set(good.regions) == {"full", "hand", "face"}
    )
    for region in ("full", "hand", "face"):
        g, b = good.regions[region], bad.regions[region]
        assert g.psnr > b.psnr + 5 and g.ssim > b.ssim and g.lpips < b.lpips
    assert good.num_gaussians == len(teacher.gaussians) and good.render_fps > 0
    assert set(good.to_dict()["per_frame"]) == {"2"}
    with pytest.raises(ValueError, match="no frames"):
        evaluate_avatar(teacher, ds, split="test_view", lpips=lpips)


def test_region_metrics_crop_to_the_region(lpips):
    torch.manual_seed(0)
    target = torch.rand(64, 64, 3)
    pred = target.clone()
    pred[:, 40:] = 0.0  # wrong only on the right
    mask = torch.zeros(64, 64)
    mask[5:10, 5:10] = 1.0  # a small region on the left: grown to 32 px, still exact there
    m = image_metrics(pred, target, lpips, mask)
    assert m["psnr"] == float("inf") and m["lpips"] == 0.0
    assert image_metrics(pred, target, lpips, torch.zeros(64, 64)) == {}
    assert image_metrics(pred, target, lpips)["psnr"] < 20


def test_table_in_the_papers_layout():
    r = EvalResult(
        split="test_pose", num_frames=4, num_gaussians=19458, render_fps=12.5, train_seconds=300.0,
        regions={"full": RegionMetrics(28.88, 0.9609, 0.04493, 4),
                 "hand": RegionMetrics(25.28, 0.9189, 0.09137, 3)},
    )  # fmt: skip
    table = metrics_table({"3DGS + body": r})
    lines = table.strip().splitlines()
    assert lines[0].startswith("| Method | N-GS | Full PSNR↑ | Full SSIM↑ | Full LPIPS↓ (×1000) | Hand PSNR↑")
    assert lines[2] == (
        "| 3DGS + body | 19,458 | 28.88 | 0.9609 | 44.93 | 25.28 | 0.9189 | 91.37 | – | – | – | 300 | 12.5 |"
    )
