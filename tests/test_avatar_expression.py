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
    (not the jaw: its offsets cost the face in new poses), and rasterize with a 0.1 px² dilation;
    the paper's rows do neither, on 3DGS's rasterizer (0.3 px²)."""
    from eva_engine.avatar.config import BLINK_ACTIONS
    from eva_engine.recipes import METHODS, PRESETS
    from eva_engine.train import preset, with_method

    for name in PRESETS:
        avatar = preset(name).avatar
        assert avatar.expression_frames and avatar.expression_colours
        assert avatar.expression_colour_actions == BLINK_ACTIONS
        assert avatar.expression_colour_spread == 0.006  # the eyeball a closing lid covers
        assert (avatar.rasterize_mode, avatar.eps2d) == ("classic", 0.1)
    for method in METHODS:
        avatar = with_method(preset("fast"), method).avatar
        assert not avatar.expression_frames and not avatar.expression_colours
        assert (avatar.rasterize_mode, avatar.eps2d) == ("classic", 0.3)


def test_the_template_face_changes_where_gaussians_are_stored_not_where_a_frame_puts_them(
    anny_model, tmp_path
):
    """An avatar on a template with an expression (``AvatarConfig.template_expression``) stores
    its Gaussians on that face, and a frame moves them by its expression's difference from it: the
    same frame poses them where the zero-expression avatar's go. Saved and loaded, the template's
    expression comes back and the pose is the same."""
    import dataclasses

    from eva_engine.avatar import Avatar, load_avatar, save_avatar, template_vertices
    from eva_engine.avatar.config import AvatarConfig

    names = list(anny_model.expression_names)
    face = torch.zeros(len(names))
    face[names.index("eyeWideLeft")] = face[names.index("eyeWideRight")] = 0.6
    face[names.index("jawOpen")] = 0.2
    cfg = AvatarConfig(sh_degree=0, init_max_gaussians=3000, mlp_width=16, pe_frequencies=2)
    shape = anny_model.shape_defaults
    neutral = Avatar.create(anny_model, shape, cfg, seed=1)
    median_cfg = dataclasses.replace(cfg, template_expression="median")
    on_face = Avatar.create(anny_model, shape, median_cfg, seed=1, expression=face)
    torch.testing.assert_close(
        on_face.gaussians.template_vertices, template_vertices(anny_model, shape, face)
    )
    moved = (on_face.gaussians.means - neutral.gaussians.means).detach().norm(dim=-1)
    assert float(moved.max()) > 1e-3  # the lids and jaw sit elsewhere on the template

    frame = anny_model.params_from_pose({"expression": {"eyeBlinkLeft": 1.0, "jawOpen": 0.5}})
    with torch.no_grad():
        expected = neutral.pose(frame).means
        torch.testing.assert_close(on_face.pose(frame).means, expected, atol=1e-5, rtol=0)
    save_avatar(on_face, tmp_path / "avatar")
    loaded = load_avatar(tmp_path / "avatar")
    torch.testing.assert_close(loaded.template_expression, on_face.template_expression)
    with torch.no_grad():
        torch.testing.assert_close(loaded.pose(frame).means, expected, atol=1e-5, rtol=0)
    try:
        AvatarConfig(template_expression="mean")
    except ValueError as err:
        assert "median" in str(err)
    else:
        raise AssertionError("an unknown template expression was accepted")


def test_gaussians_seen_through_the_eye_opening_attach_to_the_eyeball(anny_model):
    """``AvatarConfig.eye_binding``: the iris is painted in front of the coarse eyeball and
    beside the dense lid margin, so its nearest vertex is mostly a lid vertex and a blink would
    carry it down the face. Seen through the opening, it attaches to the eyeball and stays where
    it is when the lid closes; Gaussians on the lid's skin keep their lid vertex."""
    import dataclasses

    from eva_engine.avatar import Avatar
    from eva_engine.avatar.config import AvatarConfig
    from eva_engine.avatar.eye_binding import inside
    from eva_engine.body.anny_backend import SEGMENT_LABELS

    cfg = AvatarConfig(sh_degree=0, init_max_gaussians=4000, mlp_width=16, pe_frequencies=2)
    shape = anny_model.shape_defaults
    plain = Avatar.create(anny_model, shape, cfg, seed=0)
    bound = Avatar.create(anny_model, shape, dataclasses.replace(cfg, eye_binding=True), seed=0)
    openings = bound.gaussians.eye_openings
    assert len(openings) == 2 and not plain.gaussians.eye_openings
    labels = torch.as_tensor(anny_model.segment_labels)
    eyeball = {SEGMENT_LABELS.index("eye_front.L"), SEGMENT_LABELS.index("eye_front.R")}
    lid = SEGMENT_LABELS.index("head")

    # A grid over each opening, 1-4 mm in front of the eyeball's front: the painted iris.
    iris = []
    for eye in openings:
        lo, hi = eye.outline.min(dim=0).values, eye.outline.max(dim=0).values
        x, y = torch.meshgrid(torch.linspace(0, 1, 9), torch.linspace(0, 1, 5), indexing="ij")
        xy = lo + (hi - lo) * torch.stack([x.flatten(), y.flatten()], dim=-1)
        xy = xy[inside(xy, eye.outline)]
        front = bound.gaussians.template_vertices[eye.eyeball, 2].max()
        z = front + torch.linspace(-0.003, 0.001, len(xy))
        iris.append(torch.cat([xy, z[:, None]], dim=-1))
    iris = torch.cat(iris)
    # The upper lids' skin: vertices a blink moves, above the openings.
    template = bound.gaussians.template_vertices
    names = list(anny_model.expression_names)
    p = anny_model.default_params(2)
    p.expression[1, [names.index("eyeBlinkLeft"), names.index("eyeBlinkRight")]] = 1.0
    with torch.no_grad():
        shut = anny_model.canonical(p)
    travel = (shut[1] - shut[0]).norm(dim=-1)
    top = max(float(e.outline[:, 1].max()) for e in openings)
    skin = template[(labels == lid) & (travel > 0.5 * travel.max()) & (template[:, 1] > top + 0.001)]
    assert len(skin) > 4
    points = torch.cat([iris, skin])
    attached = {}
    for name, avatar in (("plain", plain), ("bound", bound)):
        g = avatar.gaussians
        with torch.no_grad():
            g.splats["means"][: len(points)] = points
        g.refresh_vertex_ids()
        attached[name] = labels[g.vertex_ids[: len(points)]]
    on_eyeball = torch.tensor([int(v) in eyeball for v in attached["bound"][: len(iris)]])
    assert bool(on_eyeball.all())
    assert sum(int(v) == lid for v in attached["plain"][: len(iris)]) > len(iris) // 4  # what this fixes
    assert bool((attached["bound"][len(iris) :] == lid).all()) and bool(
        (attached["plain"][len(iris) :] == lid).all()
    )

    blink = anny_model.params_from_pose({"expression": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0}})
    rest = anny_model.params_from_pose({})
    with torch.no_grad():
        moved = (bound.pose(blink).means - bound.pose(rest).means)[: len(points)].norm(dim=-1)
    assert float(moved[: len(iris)].max()) < 1e-6  # the iris stays with the eyeball
    assert float(moved[len(iris) :].min()) > 1e-3  # the lid comes down


def test_the_eye_opening_test_is_the_even_odd_rule():
    from eva_engine.avatar.eye_binding import inside

    square = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    points = torch.tensor([[0.5, 0.5], [1.5, 0.5], [0.5, -0.1], [0.99, 0.01], [-0.01, 0.5]])
    assert inside(points, square).tolist() == [True, False, False, True, False]
