"""GART's skinning (``avatar/skinning_field.py``): the weight field starts as the body model's
weights, its regularisers start at 0, latent bones learn a non-rigid motion the skeleton cannot
make, and an avatar with field skinning saves, reloads and renders like any other."""

from __future__ import annotations

import math

import torch
from helpers.scenes import front_camera, random_params

from eva_engine.avatar import Avatar, AvatarConfig, load_avatar, save_avatar
from eva_engine.avatar.skinning import skin_gaussians
from eva_engine.avatar.skinning_field import LatentBones, SkinningField, diffuse
from eva_engine.train import preset, with_method
from eva_engine.train.regularizers import RegularizerConfig, regularization


def two_bone_rod(n: int = 200) -> tuple[torch.Tensor, torch.Tensor]:
    """Points along x in [-0.5, 0.5] with two bones' weights varying linearly along the rod."""
    x = torch.linspace(-0.5, 0.5, n)
    points = torch.stack([x, torch.zeros(n), torch.zeros(n)], dim=-1)
    w1 = x + 0.5
    return points, torch.stack([1.0 - w1, w1], dim=-1)


def test_the_field_starts_as_the_body_weights_and_its_regularisers_at_zero():
    points, weights = two_bone_rod()
    field = SkinningField(points, weights, resolution=32, latent_bones=2)
    out = field(points)
    assert out.shape == (200, 4)
    # Interpolated body weights (a smooth field reproduces a linear one), latent channels 1e-4.
    inner = slice(20, 180)
    torch.testing.assert_close(out[inner, :2], weights[inner], atol=0.03, rtol=0)
    torch.testing.assert_close(out[:, 2:], torch.full((200, 2), 1e-4))
    torch.testing.assert_close(out[:, :2].sum(dim=1), torch.ones(200), atol=1e-5, rtol=0)
    tv, latent_tv = field.total_variation()
    norm, _ = field.magnitude()
    assert tv.item() == 0.0 and latent_tv.item() == 0.0 and norm.item() == 0.0
    # Far outside the box: the border's weights, finite.
    far = field(torch.tensor([[100.0, -100.0, 100.0], [0.0, 0.0, -1e6]]))
    assert torch.all(torch.isfinite(far)) and torch.allclose(far[:, :2].sum(dim=1), torch.ones(2), atol=1e-5)


def test_diffusion_keeps_weights_normalised():
    g = torch.Generator().manual_seed(0)
    grid = torch.rand(1, 5, 4, 6, 6, generator=g)
    grid = grid / grid.sum(dim=1, keepdim=True)
    out = diffuse(grid, steps=10)
    torch.testing.assert_close(out.sum(dim=1), torch.ones(1, 4, 6, 6))
    assert out[:, :, 1:-1, 1:-1, 1:-1].std() < grid[:, :, 1:-1, 1:-1, 1:-1].std()  # smoother
    torch.testing.assert_close(out[:, :, 0], grid[:, :, 0])  # the border only renormalised


def test_latent_bones_start_at_the_identity():
    bones = LatentBones(pose_dim=6, bones=3)
    t = bones(torch.zeros(1, 2, 3))
    torch.testing.assert_close(t, torch.eye(4).expand(3, 4, 4), atol=1e-2, rtol=0)
    torch.testing.assert_close(t[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(3, 4))


def test_latent_bones_learn_a_non_rigid_motion_the_skeleton_cannot_make():
    """A 'skirt' ring sways forward by an amount set by the pose while the skeleton's only bone
    (the root) stays still: LBS on the skeleton cannot follow it. From GART's start (latent weights
    1e-4, latent bones at the identity) the field's latent channel and the pose MLP learn it."""
    angle = torch.linspace(0, 2 * math.pi, 64)[:-1]
    skirt = torch.stack([0.3 * angle.cos(), torch.zeros_like(angle), 0.3 * angle.sin()], dim=-1)
    field = SkinningField(skirt, torch.ones(len(skirt), 1), resolution=8, latent_bones=1)
    bones = LatentBones(pose_dim=3, bones=1, width=32, depth=2)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(len(skirt), 4)
    opt = torch.optim.Adam([*field.parameters(), *bones.parameters()], lr=3e-3)

    def error(pose: torch.Tensor) -> torch.Tensor:
        sway = skirt + torch.stack([torch.zeros(()), torch.zeros(()), 0.3 * pose[0, 0, 1]])
        transforms = torch.cat([torch.eye(4)[None], torch.eye(4)[None] @ bones(pose)])  # root, latent
        posed, _, _ = skin_gaussians(skirt, quats, field(skirt), transforms)
        return ((posed - sway) ** 2).sum(dim=-1).mean()

    test_poses = [torch.tensor([[[0.0, v, 0.0]]]) for v in (-0.4, -0.2, 0.3, 0.5)]
    with torch.no_grad():
        before = sum(float(error(p)) for p in test_poses)  # = the skeleton alone, to ~1e-4
    g = torch.Generator().manual_seed(1)
    for _ in range(300):
        pose = torch.zeros(1, 1, 3)
        pose[0, 0, 1] = torch.rand((), generator=g) - 0.5
        loss = error(pose)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = sum(float(error(p)) for p in test_poses)
        latent_weight = field(skirt)[:, 1].mean()
    assert after < 0.01 * before, (before, after)
    assert latent_weight.abs() > 1e-2  # the skirt's points now hang on the latent bone


def test_regularisers_are_finite_with_gradients(anny_model):
    cfg = with_method(preset("tiny"), "gart+body")
    cfg_avatar = AvatarConfig(**{**cfg.avatar.to_dict(), "field_resolution": 16, "init_max_gaussians": 300})
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, cfg_avatar, seed=0)
    assert regularization(avatar, RegularizerConfig(lambda_thin=0.0)).item() == 0.0  # none active
    total = regularization(avatar, cfg.regularizers)
    total.backward()
    assert torch.isfinite(total) and total > 0  # the KNN std and small-scale terms
    assert torch.isfinite(avatar.skinning_field.correction.grad).all()
    assert torch.isfinite(avatar.gaussians.splats["sh0"].grad).all()


def test_a_field_skinned_avatar_saves_reloads_and_renders_identically(tmp_path, anny_model):
    config = AvatarConfig(
        init_max_gaussians=400,
        sh_degree=1,
        skinning="field",
        weight_offsets=False,
        pose_refine=False,
        field_resolution=16,
        latent_bones=2,
        init_opacity=0.99,
    )
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, config, seed=0)
    torch.manual_seed(0)
    with torch.no_grad():
        for p in avatar.mlp_parameters():
            p.add_(0.01 * torch.randn_like(p))
    assert set(avatar.networks()) == {"skinning_field", "latent_bones"}
    back = load_avatar(save_avatar(avatar, tmp_path / "gart"), body=anny_model)
    cam = front_camera(40)
    for seed in (1, 2):
        params = random_params(anny_model, 1, seed)
        assert torch.equal(back.render(params, cam), avatar.render(params, cam))


def test_the_gart_method_switches_skinning_objective_and_thresholds():
    base = preset("tiny")
    gart = with_method(base, "gart+body")
    assert gart.avatar.skinning == "field" and gart.avatar.latent_bones == 4
    assert not gart.avatar.weight_offsets and not gart.avatar.pose_refine
    assert (gart.loss.lambda_ssim, gart.loss.lambda_lpips, gart.loss.lambda_mask) == (0.1, 0.0, 0.0)
    assert gart.strategy.grow_grad2d == 1e-4 and gart.strategy.prune_opa == 0.1
    assert gart.regularizers.active and gart.strategy.refine_every == base.strategy.refine_every
    back = with_method(gart, "eva")  # switching back restores the method's own choices
    assert back.avatar == with_method(base, "eva").avatar and not back.regularizers.active
    assert back.strategy == with_method(base, "eva").strategy
