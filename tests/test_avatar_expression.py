"""Expression driving: a pose JSON with facial-action values visibly changes the rendered face,
where that action acts (jawOpen below the eyes, browInnerUp above them)."""

from __future__ import annotations

import dataclasses

import torch
from helpers.scenes import teacher_avatar

from eva_engine.avatar import Camera
from eva_engine.geometry import project_points, to_camera
from eva_engine.render import look_at


def face_camera(body, size: int) -> Camera:
    """A close-up of the rest-pose face from the front."""
    with torch.no_grad():
        kp = body.keypoints(body(body.default_params(1)))[0]
    names = list(body.keypoint_names)
    centre = 0.5 * (kp[names.index("face_left_iris")] + kp[names.index("face_mouth_left")])
    centre = torch.tensor([0.0, float(centre[1]), float(centre[2])])
    f = size * 0.4 / 0.25  # a 25 cm wide view at 40 cm
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    view = look_at((0.0, float(centre[1]), float(centre[2]) + 0.4), tuple(centre.tolist()))
    return Camera(K, view, size, size)


def project_y(body, camera: Camera, name: str) -> float:
    with torch.no_grad():
        kp = body.keypoints(body(body.default_params(1)))[0, [list(body.keypoint_names).index(name)]]
    return float(project_points(to_camera(kp, camera.viewmat), camera.K)[0, 1])


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


def dark_eyes_avatar(body, footprint: float, expression_frames: bool = False):
    """The teacher on every surface vertex with dark eyeballs and light skin, its footprints
    exp(-``footprint``) times the teacher's."""
    from eva_engine.align.face_mesh import skin_faces

    avatar = teacher_avatar(body, n=body.num_vertices)
    avatar.config = dataclasses.replace(avatar.config, expression_frames=expression_frames)
    g = avatar.gaussians
    faces = body.faces.cpu().numpy()
    skin = torch.zeros(body.num_vertices, dtype=torch.bool)
    skin[torch.from_numpy(faces[skin_faces(faces, body.num_vertices)]).flatten()] = True
    eyeball = ~skin[g.vertex_ids] & (g.part_ids == 2)  # the face's other pieces: eyes (and mouth)
    assert int(eyeball.sum()) > 50
    rgb = torch.where(eyeball[:, None], torch.full((1, 3), 0.02), torch.full((1, 3), 0.9))
    with torch.no_grad():
        g.splats["sh0"][:, 0] = (rgb - 0.5) / 0.28209479177387814
        g.splats["scales"][:] -= footprint
    return avatar


def dark_eye_pixels(avatar, body, blink: float, size: int = 160) -> int:
    """Dark pixels in the rows of the eyes of a frontal close-up with both eyes' blink at ``blink``."""
    cam = face_camera(body, size)
    eye_y = project_y(body, cam, "face_left_iris")
    pose = {"expression": {"eyeBlinkLeft": blink, "eyeBlinkRight": blink}}
    img = avatar.render(body.params_from_pose(pose), cam, torch.ones(3))
    band = img[max(int(eye_y) - 12, 0) : int(eye_y) + 12]
    return int((band.mean(-1) < 0.3).sum())


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
    from eva_engine.recipes import METHODS, PRESETS
    from eva_engine.train import preset, with_method

    assert all(preset(name).avatar.expression_frames for name in PRESETS)
    assert not any(with_method(preset("fast"), m).avatar.expression_frames for m in METHODS)
