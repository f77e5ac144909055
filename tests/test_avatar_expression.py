"""Expression driving: a pose JSON with facial-action values visibly changes the rendered face,
where that action acts (jawOpen below the eyes, browInnerUp above them)."""

from __future__ import annotations

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


def test_a_fitted_blink_closes_the_rendered_eye(anny_model):
    """An avatar with dark eyeballs and light skin, rendered with the blink a fit reports: the
    lids' Gaussians follow the blendshape down over the eyeballs, so the dark pixels go."""
    from eva_engine.align.face_mesh import skin_faces

    avatar = teacher_avatar(anny_model, n=anny_model.num_vertices)
    g = avatar.gaussians
    faces = anny_model.faces.cpu().numpy()
    skin = torch.zeros(anny_model.num_vertices, dtype=torch.bool)
    skin[torch.from_numpy(faces[skin_faces(faces, anny_model.num_vertices)]).flatten()] = True
    eyeball = ~skin[g.vertex_ids] & (g.part_ids == 2)  # the face's other pieces: eyes (and mouth)
    assert int(eyeball.sum()) > 50
    rgb = torch.where(eyeball[:, None], torch.full((1, 3), 0.02), torch.full((1, 3), 0.9))
    with torch.no_grad():
        g.splats["sh0"][:, 0] = (rgb - 0.5) / 0.28209479177387814
        g.splats["scales"][:] -= 0.5
    size = 160
    cam = face_camera(anny_model, size)
    eye_y = project_y(anny_model, cam, "face_left_iris")

    def dark_eye_pixels(blink: float) -> int:
        pose = {"expression": {"eyeBlinkLeft": blink, "eyeBlinkRight": blink}}
        img = avatar.render(anny_model.params_from_pose(pose), cam, torch.ones(3))
        band = img[max(int(eye_y) - 12, 0) : int(eye_y) + 12]  # the rows of the eyes
        return int((band.mean(-1) < 0.3).sum())

    open_eyes, closed = dark_eye_pixels(0.0), dark_eye_pixels(1.0)
    assert open_eyes > 20, open_eyes
    assert closed < 0.3 * open_eyes, (open_eyes, closed)
