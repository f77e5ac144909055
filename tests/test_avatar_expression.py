"""Expression driving: a pose JSON with facial-action values visibly changes the rendered face,
where that action acts (jawOpen below the eyes, browInnerUp above them)."""

from __future__ import annotations

import torch
from helpers.scenes import dark_eye_pixels, dark_eyes_avatar, face_camera, project_y, teacher_avatar


def fine_striped_avatar(body):
    """The teacher on every surface vertex, its face painted with 8 mm horizontal stripes, so a
    brow that moves by a few millimetres changes pixels (smooth colours would hide it)."""
    avatar = teacher_avatar(body, n=body.num_vertices)
    g = avatar.gaussians
    y = g.means[:, 1:2].detach()
    stripes = (0.5 + 0.45 * torch.sin(2 * torch.pi * y / 0.008)).expand(-1, 3)
    face = (g.part_ids == 2)[:, None]
    with torch.no_grad():
        sh0 = torch.where(face, (stripes - 0.5) / 0.28209479177387814, g.splats["sh0"][:, 0])
        g.splats["sh0"][:, 0] = sh0
        g.splats["scales"][:] -= 0.5  # back to vertex-spacing footprints
    return avatar


def test_facial_actions_in_a_pose_json_change_the_face_where_they_act(anny_model):
    avatar = fine_striped_avatar(anny_model)
    size = 128
    cam = face_camera(anny_model, size)
    white = torch.ones(3)

    def render(pose: dict) -> torch.Tensor:
        return avatar.render(anny_model.params_from_pose(pose), cam, white)

    neutral = render({})
    eye_y = project_y(anny_model, cam, "face_left_iris")
    mouth_y = project_y(anny_model, cam, "face_mouth_left")
    assert 0 < eye_y < mouth_y < size  # the close-up shows eyes above the mouth
    rows = torch.arange(size).float()[:, None].expand(size, size)
    for action, below_eyes in (("jawOpen", True), ("browInnerUp", False)):
        changed = (render({"expression": {action: 1.0}}) - neutral).abs().amax(-1) > 0.05  # [H, W]
        assert int(changed.sum()) > 30, f"{action} does not change the face visibly"
        centre = float(rows[changed].mean())
        if below_eyes:
            assert centre > eye_y, (action, centre, eye_y)  # the jaw and mouth move
        else:
            assert centre < mouth_y and float(rows[changed].min()) < eye_y, (action, centre)  # the brows
    # Bad names are refused with the valid ones listed, never ignored.
    try:
        anny_model.params_from_pose({"expression": {"jawOpenn": 1.0}})
    except ValueError as err:
        assert "jawOpen" in str(err)
    else:
        raise AssertionError("an unknown facial action was accepted")


def test_a_fitted_blink_closes_the_rendered_eye(anny_model):
    """Rendered with the blink a fit reports, the lids' Gaussians follow the blendshape down over
    the eyeballs, so the dark pixels go."""
    avatar = dark_eyes_avatar(anny_model, footprint=0.5)
    open_eyes, closed = dark_eye_pixels(avatar, anny_model, 0.0), dark_eye_pixels(avatar, anny_model, 1.0)
    assert open_eyes > 20, open_eyes
    assert closed < 0.3 * open_eyes, (open_eyes, closed)


def test_lid_gaussians_stretch_and_turn_with_a_closing_lid(anny_model):
    """Gaussians sized for the open lid leave the eye showing through a closed one when they only
    move with their vertex; carried by the skin's frame (``expression_frames``) they grow with the
    lid's area and face the camera as the lid does, and the closed eye is covered."""
    offset_only = dark_eyes_avatar(anny_model, footprint=1.0)
    framed = dark_eyes_avatar(anny_model, footprint=1.0, expression_frames=True)
    open_eyes = dark_eye_pixels(offset_only, anny_model, 0.0)
    assert open_eyes > 20 and dark_eye_pixels(framed, anny_model, 0.0) == open_eyes  # no expression: same
    assert dark_eye_pixels(offset_only, anny_model, 1.0) > 0.5 * open_eyes  # the gap this fixes
    assert dark_eye_pixels(framed, anny_model, 1.0) < 0.1 * open_eyes


def test_the_products_presets_carry_gaussians_by_the_skin_and_the_papers_methods_do_not():
    """The presets move the skin's Gaussians by its frame and recolour the lids with the blinks
    (not the jaw: its offsets cost the face in new poses); the paper's rows do neither."""
    from eva_engine.avatar.config import BLINK_ACTIONS
    from eva_engine.recipes import METHODS, PRESETS
    from eva_engine.train import preset, with_method

    for name in PRESETS:
        avatar = preset(name).avatar
        assert avatar.expression_frames and avatar.expression_colours
        assert avatar.expression_colour_actions == BLINK_ACTIONS
        assert avatar.expression_colour_spread == 0.006  # the eyeball a closing lid covers
    for method in METHODS:
        avatar = with_method(preset("fast"), method).avatar
        assert not avatar.expression_frames and not avatar.expression_colours
