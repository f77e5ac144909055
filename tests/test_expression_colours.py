"""Colours that change with the expression (``avatar/expression_colours.py``): exact rest colours
at zero expression, offsets only where an action moves the skin, kept through saving and density
control, bounded, and learnt: an eye painted on the lid can be recoloured to a closed lid."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from helpers.scenes import dark_eye_pixels, dark_eyes_avatar, face_camera, teacher_scene

from eva_engine.avatar import Avatar
from eva_engine.avatar.config import REVEALING_ACTIONS, AvatarConfig
from eva_engine.avatar.expression_colours import (
    MAX_OFFSET,
    action_reach,
    clamp_offsets,
    expression_sh0,
    revealing_actions,
)
from eva_engine.avatar.io import load_avatar, save_avatar
from eva_engine.render.sh import SH_C0
from eva_engine.train import preset, train_avatar
from eva_engine.train.regularizers import RegularizerConfig, colour_offsets, regularization
from eva_engine.train.strategy.ops import duplicate, remove


def with_expression_colours(avatar: Avatar) -> Avatar:
    """``avatar`` with offsets for the three revealing actions (the presets take the blinks only)."""
    config = dataclasses.replace(
        avatar.config, expression_colours=True, expression_colour_actions=REVEALING_ACTIONS
    )
    return Avatar(avatar.body, avatar.gaussians, avatar.shape, config)


def blink_params(body, blink: float):
    return body.params_from_pose({"expression": {"eyeBlinkLeft": blink, "eyeBlinkRight": blink}})


def test_an_action_recolours_only_the_skin_it_moves(anny_model):
    names = list(anny_model.expression_names)
    actions = revealing_actions(names, REVEALING_ACTIONS)
    assert [names[i] for i in actions] == ["eyeBlinkLeft", "eyeBlinkRight", "jawOpen"]
    smplx_names = [f"expr_{i}" for i in range(10)]  # PCA coefficients: none named, none recoloured
    assert revealing_actions(smplx_names, REVEALING_ACTIONS) == []
    assert revealing_actions(smplx_names, None) == list(range(10))
    assert revealing_actions(names, None) == list(range(len(names)))
    reach = action_reach(anny_model, anny_model.shape_defaults, actions)  # [V, K]
    assert reach.shape == (anny_model.num_vertices, 3) and reach.dtype == torch.bool
    blink, jaw = reach[:, 0], reach[:, 2]
    face = anny_model.part_ids == 2
    assert 50 < int(blink.sum()) < 2000 and bool(face[blink].all())  # the lids, no hand or body
    assert int(jaw.sum()) > int(blink.sum()) and int((blink & jaw).sum()) < 0.2 * int(blink.sum())
    with torch.no_grad():  # Anny's jawOpen moves the nose a little: not enough to recolour it
        kp = anny_model.keypoints(anny_model(anny_model.default_params(1)))[0]
        tip = kp[list(anny_model.keypoint_names).index("face_nose_tip")]
        rest = anny_model.canonical(anny_model.default_params(1))[0]
    assert not bool(jaw[(rest - tip).norm(dim=-1) < 0.01].any())

    n, e = 5, len(names)
    sh0, offsets = torch.randn(n, 1, 3), torch.randn(n, e, 3)
    rows = torch.zeros(n, e, dtype=torch.bool)
    rows[0, 3] = rows[1, 3] = True
    coefficients, scale = torch.zeros(e), torch.ones(e)
    coefficients[3] = 0.5
    out = expression_sh0(sh0, offsets, coefficients, rows, scale)
    assert torch.equal(out[2:], sh0[2:])  # not reached: the rest colour
    assert torch.allclose(out[:2, 0], sh0[:2, 0] + 0.5 * offsets[:2, 3])
    # Scaled to the training frames' range, and no further: 0.5 of a 0.25 range is the full offset.
    scale[3] = 0.25
    out = expression_sh0(sh0, offsets, coefficients, rows, scale)
    assert torch.allclose(out[:2, 0], sh0[:2, 0] + offsets[:2, 3])


def test_a_spread_also_recolours_what_the_moved_skin_covers(anny_model):
    """With ``spread`` a blink also reaches the vertices within that distance of the lid it moves
    (the eyeball's front, which it covers but does not move), and no longer what Anny's blink
    moves far from the eye (the mouth's cavity, the other eye's socket)."""
    from eva_engine.body.anny_backend import SEGMENT_LABELS

    actions = revealing_actions(list(anny_model.expression_names), ("eyeBlinkLeft",))
    shape = anny_model.shape_defaults
    moved = action_reach(anny_model, shape, actions)[:, 0]
    spread = action_reach(anny_model, shape, actions, spread=0.006)[:, 0]
    assert torch.equal(action_reach(anny_model, shape, actions, spread=0.0)[:, 0], moved)
    labels = torch.as_tensor(anny_model.segment_labels)
    eye = labels == SEGMENT_LABELS.index("eye_front.L")
    mouth = labels == SEGMENT_LABELS.index("mouth_cavity")
    other_eye = labels == SEGMENT_LABELS.index("eye_cavity.R")
    assert not bool(moved[eye].any()) and int(spread[eye].sum()) > 0.5 * int(eye.sum())
    assert bool(moved[mouth].any()) and not bool(spread[mouth].any())
    assert bool(moved[other_eye].any()) and not bool(spread[other_eye].any())
    with torch.no_grad():
        rest = anny_model.canonical(anny_model.default_params(1))[0]
    kept = moved & spread
    assert int(kept.sum()) > 0.8 * int((moved & ~mouth & ~other_eye).sum())
    gap = torch.cdist(rest[spread & ~moved], rest[kept]).amin(dim=1)
    assert float(gap.max()) < 0.006
    with pytest.raises(ValueError, match="expression_colour_spread"):
        AvatarConfig(expression_colour_spread=-0.001)


def test_rest_colours_exactly_at_zero_expression_and_saved_offsets_render_the_same(anny_model, tmp_path):
    base = dark_eyes_avatar(anny_model, footprint=0.5)
    avatar = with_expression_colours(base)
    g = avatar.gaussians
    assert g.splats["sh0_expression"].shape == (len(g), 3, 3)  # the lids' two actions and the jaw
    neutral = anny_model.default_params(1)
    assert torch.equal(avatar.pose(neutral).sh, g.sh())
    with torch.no_grad():
        g.splats["sh0_expression"].normal_(0.0, 0.5, generator=torch.Generator().manual_seed(1))
    assert torch.equal(avatar.pose(neutral).sh, g.sh())  # offsets scale with the coefficients
    closed = avatar.pose(blink_params(anny_model, 1.0)).sh
    changed = (closed != g.sh()).any(-1).any(-1)
    lids = avatar.expression_reach[g.vertex_ids].any(-1)
    assert bool(changed.any()) and not bool((changed & ~lids).any())

    # A blink past the training frames' widest recolours no further (the lid still moves).
    expression = torch.zeros(4, len(anny_model.expression_names))
    expression[1, list(anny_model.expression_names).index("eyeBlinkLeft")] = 0.4
    avatar.set_expression_range(expression)
    assert torch.allclose(avatar.expression_range, torch.tensor([0.4, 0.05, 0.05]))
    closed = avatar.pose(blink_params(anny_model, 1.0)).sh
    assert torch.equal(closed, avatar.pose(blink_params(anny_model, 0.4)).sh)

    save_avatar(avatar, tmp_path / "a")
    loaded = load_avatar(tmp_path / "a")
    assert torch.equal(loaded.gaussians.splats["sh0_expression"], g.splats["sh0_expression"])
    assert torch.equal(loaded.expression_range, avatar.expression_range)
    assert torch.allclose(loaded.pose(blink_params(anny_model, 1.0)).sh, closed)
    plain = load_avatar(save_avatar(dark_eyes_avatar(anny_model, 0.5), tmp_path / "b"))  # none
    assert "sh0_expression" not in plain.gaussians.splats


def test_a_model_without_the_named_actions_trains_and_saves_with_no_offsets(smplx_model, tmp_path):
    """SMPL-X's expression coefficients are unnamed PCA components, each moving the whole face: the
    presets' blink colours give its avatar no offsets, and it trains, saves and loads as usual."""
    ds, _ = teacher_scene(smplx_model, n_frames=3, size=32)
    cfg = preset("tiny", iterations=20)
    assert cfg.avatar.expression_colours
    result = train_avatar(ds, cfg, body=smplx_model)
    g = result.avatar.gaussians
    assert g.splats["sh0_expression"].shape == (len(g), 0, 3)
    assert result.losses[-1] < result.losses[0]
    params = smplx_model.default_params(1)
    params.expression[:] = 2.0
    assert torch.equal(result.avatar.pose(params).sh, g.sh())
    loaded = load_avatar(save_avatar(result.avatar, tmp_path / "a"), body=smplx_model)
    assert loaded.config.expression_colours and len(loaded.expression_range) == 0


def test_density_control_keeps_the_offsets_with_their_gaussians(anny_model):
    avatar = with_expression_colours(dark_eyes_avatar(anny_model, footprint=0.5))
    g = avatar.gaussians
    with torch.no_grad():
        g.splats["sh0_expression"].copy_(torch.arange(len(g), dtype=torch.float32)[:, None, None])
    mask = torch.zeros(len(g), dtype=torch.bool)
    mask[[3, 7]] = True
    duplicate(g, {}, {}, mask)
    assert torch.equal(g.splats["sh0_expression"][-2:, 0, 0], torch.tensor([3.0, 7.0]))
    remove(g, {}, {}, torch.arange(len(g)) < 2)
    assert float(g.splats["sh0_expression"][0, 0, 0].detach()) == 2.0


def test_offsets_stay_bounded_and_their_gradients_finite_at_extreme_coefficients(anny_model):
    avatar = with_expression_colours(dark_eyes_avatar(anny_model, footprint=0.5))
    offsets = avatar.gaussians.splats["sh0_expression"]
    with torch.no_grad():
        offsets.fill_(1e6)
    clamp_offsets(offsets)
    assert float(offsets.detach().abs().max()) == pytest.approx(MAX_OFFSET)
    params = blink_params(anny_model, 1.0)
    params.expression = params.expression * 1e3  # far outside any fit's range
    sh = avatar.pose(params).sh
    sh.sum().backward()
    assert torch.isfinite(sh).all() and torch.isfinite(offsets.grad).all()


def test_the_ridge_costs_the_recoloured_pairs_colour_change_and_nothing_else(anny_model):
    avatar = with_expression_colours(dark_eyes_avatar(anny_model, footprint=0.5))
    g = avatar.gaussians
    reach = avatar.expression_reach[g.vertex_ids]  # [N, K]
    offsets = g.splats["sh0_expression"]
    with torch.no_grad():
        offsets.fill_(2.0)
        offsets[~reach] = 1e3  # never rendered: must not count
    cost = colour_offsets(avatar)
    assert float(cost.detach()) == pytest.approx(3 * (2.0 * SH_C0) ** 2, rel=1e-6)
    cost.backward()
    assert torch.isfinite(offsets.grad).all() and not bool(offsets.grad[~reach].any())
    plain = dark_eyes_avatar(anny_model, footprint=0.5)  # no offsets
    assert float(colour_offsets(plain)) == 0.0
    on = RegularizerConfig(lambda_thin=0.0, lambda_colour_offsets=0.5)
    assert on.active
    assert float(regularization(avatar, on).detach()) == pytest.approx(0.5 * float(cost.detach()))


def test_an_eye_painted_on_the_lid_learns_to_close(anny_model):
    """The failure on real video: the eye is drawn by the lid's own Gaussians, so a blink drags a
    dark eye down the face. Trained on one closed-eye frame, the offsets turn the lid to skin
    there, and the open eye (no expression) is untouched."""
    size = 160
    truth = dark_eyes_avatar(anny_model, footprint=0.5)  # a skin-coloured lid over dark eyeballs
    painted = with_expression_colours(dark_eyes_avatar(anny_model, footprint=0.5))
    g = painted.gaussians
    lids = painted.expression_reach[g.vertex_ids][:, 0]  # eyeBlinkLeft's
    with torch.no_grad():  # the lids painted dark, like the iris and lash line a video shows there
        g.splats["sh0"][lids] = (0.02 - 0.5) / 0.28209479177387814
    open_before = dark_eye_pixels(painted, anny_model, 0.0, size)
    painted_closed = dark_eye_pixels(painted, anny_model, 1.0, size)
    truth_closed = dark_eye_pixels(truth, anny_model, 1.0, size)
    assert painted_closed > 3 * max(truth_closed, 10)  # the dark smear of a painted eye

    cam, white = face_camera(anny_model, size), torch.ones(3)
    closed = blink_params(anny_model, 1.0)
    with torch.no_grad():
        target = truth(closed, cam, white).image
    opt = torch.optim.Adam([g.splats["sh0_expression"]], lr=0.2)
    for _ in range(30):
        loss = (painted(closed, cam, white).image - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        clamp_offsets(g.splats["sh0_expression"])
    assert dark_eye_pixels(painted, anny_model, 1.0, size) < 0.3 * painted_closed
    assert dark_eye_pixels(painted, anny_model, 0.0, size) == open_before
