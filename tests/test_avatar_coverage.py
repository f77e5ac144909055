"""What an avatar saw in training (``avatar.coverage``): the camera's direction about the body
(the body's own turn undone), each joint's and facial action's range, the warnings a render
beyond them gets, and the record in ``avatar.json``."""

from __future__ import annotations

import math

import pytest
import torch

from eva_engine.avatar import Avatar, AvatarConfig, TrainingRecord, read_avatar_meta, save_avatar
from eva_engine.avatar.coverage import (
    Coverage,
    nearest_pose_distance,
    rest_root,
    rotation_distance,
    view_angles,
)
from eva_engine.render.camera import orbit_camera


def _frames(model, yaws_deg, body_turns):
    params = model.default_params(len(yaws_deg))
    params.root_orient[:, 1] = torch.tensor(body_turns, dtype=params.root_orient.dtype)
    root = rest_root(model, params.shape[:1])
    views = torch.stack([orbit_camera(y, 0.0, 2.5, target=root.tolist()) for y in yaws_deg]).float()
    return params, views, root


def test_view_angles_follow_the_camera_and_undo_the_body_turn(anny_model):
    params, views, root = _frames(anny_model, [0.0, 30.0, 30.0, -60.0], [0.0, 0.0, 0.3, -0.5])
    yaw, pitch = view_angles(params, views, root)
    expected = [0.0, 30.0, 30.0 - math.degrees(0.3), -60.0 + math.degrees(0.5)]
    assert yaw.tolist() == pytest.approx(expected, abs=1e-3)
    assert pitch.abs().max() < 1e-3
    above = orbit_camera(0.0, 40.0, 2.5, target=root.tolist()).float()
    assert float(view_angles(params[[0]], above, root)[1][0]) == pytest.approx(40.0, abs=1e-3)


def test_rotation_distance_and_the_nearest_pose():
    a = torch.tensor([[0.0, 0.0, 0.5], [0.3, 0.0, 0.0]])
    assert rotation_distance(a, a).abs().max() < 1e-3  # acos near 1 costs precision, not more
    assert float(rotation_distance(a[0], torch.zeros(3))) == pytest.approx(0.5, abs=1e-5)
    train = torch.zeros(3, 4, 3)
    train[1, 2] = torch.tensor([0.0, 0.8, 0.0])
    train[2, 0] = torch.tensor([0.2, 0.0, 0.0])
    test = torch.zeros(2, 4, 3)
    test[0, 2] = torch.tensor([0.0, 0.7, 0.0])  # nearest: frame 1, 0.1 rad off
    test[1, 0] = torch.tensor([1.0, 0.0, 0.0])  # nearest: frame 2, 0.8 rad
    dist, idx = nearest_pose_distance(test, train)
    assert idx.tolist() == [1, 2] and dist.tolist() == pytest.approx([0.1, 0.8], abs=1e-4)
    only = torch.tensor([True, False, False, False])  # joint 0 alone: test 0 matches frame 0 exactly
    dist, idx = nearest_pose_distance(test, train, only)
    assert idx[0] == 0 and float(dist[0]) == pytest.approx(0.0, abs=1e-3)


def test_warnings_name_what_lies_beyond_the_training_range(anny_model):
    params, views, root = _frames(anny_model, [-10.0, 0.0, 10.0], [0.0, 0.0, 0.0])
    j = anny_model.pose_joint_names.index("lowerarm01.R")
    params.joints[:, j, 1] = torch.tensor([0.2, 0.5, 0.8])
    e = anny_model.expression_names.index("jawOpen")
    params.expression[:, e] = torch.tensor([0.0, 0.1, 0.2])
    coverage = Coverage.of_frames(anny_model, params, views)
    assert coverage.frames == 3 and coverage.yaw_deg.min == pytest.approx(-10.0, abs=1e-3)
    assert coverage.joints["lowerarm01.R"][1].max == pytest.approx(0.8)
    inside = params[[1]]
    assert coverage.warnings(anny_model, inside, views[1]) == []
    # Small excursions stay within the margins (10 deg, 0.35 rad, 0.25).
    near = anny_model.params_from_pose(
        {"joints": {"lowerarm01.R": [0, 1.0, 0]}, "expression": {"jawOpen": 0.4}}
    )
    assert coverage.warnings(anny_model, near, orbit_camera(18.0, 8.0, 2.5, target=root.tolist())) == []
    far = anny_model.params_from_pose(
        {"joints": {"lowerarm01.R": [0, 1.6, 0], "upperleg01.L": [0.9, 0, 0]}, "expression": {"jawOpen": 0.9}}
    )
    side = orbit_camera(-90.0, 0.0, 2.5, target=root.tolist())
    warnings = coverage.warnings(anny_model, far, side)
    assert len(warnings) == 3
    assert "yaw -90 deg (to the subject's right)" in warnings[0] and "-10 to 10" in warnings[0]
    assert "upperleg01.L (52 deg)" in warnings[1] and "lowerarm01.R (46 deg)" in warnings[1]
    assert "jawOpen" in warnings[2]
    above = orbit_camera(0.0, 60.0, 2.5, target=root.tolist())
    assert "from above" in coverage.warnings(anny_model, inside, above)[0]


def test_coverage_survives_avatar_json(anny_model, tmp_path):
    params, views, _ = _frames(anny_model, [0.0, 15.0], [0.1, -0.1])
    coverage = Coverage.of_frames(anny_model, params, views)
    cfg = AvatarConfig(init_max_gaussians=200, mlp_width=8, pe_frequencies=1, sh_degree=0)
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, cfg)
    save_avatar(avatar, tmp_path / "a", TrainingRecord(coverage=coverage))
    assert read_avatar_meta(tmp_path / "a").coverage == coverage
    save_avatar(avatar, tmp_path / "b")  # an avatar made without a record: no coverage, no warnings
    assert read_avatar_meta(tmp_path / "b").coverage is None
