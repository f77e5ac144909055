""" "Model only what a scene needs": a video whose frames never show the hands ends with no hand
Gaussians, while the parts it shows keep theirs."""

from __future__ import annotations

import dataclasses

import torch
from helpers.scenes import SceneDataset, front_camera, teacher_scene

from eva_engine.geometry import project_points, to_camera
from eva_engine.train import LossConfig, preset, train_avatar, with_method

HAND = 1


def pixel_rows(avatar, params, camera, part: int) -> torch.Tensor:
    """[M] image rows of the posed centres of ``part``'s Gaussians."""
    posed = avatar.pose(params)
    sel = avatar.gaussians.part_ids == part
    return project_points(to_camera(posed.means.detach()[sel], camera.viewmat), camera.K)[:, 1]


def head_and_shoulders(ds: SceneDataset, rows: int) -> SceneDataset:
    """The scene cropped to its top ``rows`` image rows (same intrinsics)."""
    frames = [
        dataclasses.replace(
            f, image=f.image[:rows], mask=f.mask[:rows], regions={k: m[:rows] for k, m in f.regions.items()}
        )
        for f in ds.frames
    ]
    return dataclasses.replace(ds, frames=frames)


def test_a_video_without_hands_spends_no_gaussians_on_them(anny_model):
    ds, teacher = teacher_scene(anny_model, n_frames=6, size=128, amplitude=0.1)
    cam = front_camera(128)
    top_of_hands = min(float(pixel_rows(teacher, ds.params[i], cam, HAND).min()) for i in range(len(ds)))
    rows = int(top_of_hands) - 4  # a margin for the Gaussians' footprint
    assert rows >= 40, "the teacher's hands reach the head: the scene cannot hide them"
    cropped = head_and_shoulders(ds, rows)
    hands = ("hand_left", "hand_right")
    assert all(float(cropped[i].regions[h].sum()) == 0 for i in range(len(cropped)) for h in hands)

    base = preset("tiny", iterations=30, loss=LossConfig(lambda_lpips=0.0))
    base = dataclasses.replace(
        base, strategy=dataclasses.replace(base.strategy, refine_start_iter=10, refine_every=10)
    )
    for method in ("3dgs+body", "eva"):
        result = train_avatar(cropped, with_method(base, method), body=anny_model)
        per_part = result.gaussians_per_part
        assert per_part["before"]["hand"] > 0
        assert per_part["after"]["hand"] == 0, per_part
        assert per_part["after"]["body"] > 0 and per_part["after"]["face"] > 0
        final = result.refinements[-1]
        assert final["step"] == base.iterations and final["unseen_parts"] == ["hand"]
        assert len(result.avatar.gaussians) == sum(per_part["after"].values())
        # The avatar still renders (the hands are simply absent).
        out = result.avatar(ds.params[0], cam, torch.ones(3))
        assert torch.isfinite(out.image).all()
