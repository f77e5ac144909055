"""The animation engine's pieces on their own: rotations over time (quaternion round trips, sign
continuity, smoothing that keeps a held pose, resampling), retargeting between two bodies, pose
sequences from JSON, and the pose controls the web page builds its sliders from."""

from __future__ import annotations

import math

import pytest
import torch

from eva_engine.animate import DrivingError, body_height, driving_from_poses, retarget
from eva_engine.animate.controls import pose_controls, pose_from_controls
from eva_engine.animate.retarget import recenter, rest_root
from eva_engine.animate.timing import (
    axis_angle_to_quat,
    continuous_quats,
    frame_times,
    quat_to_axis_angle,
    resample_params,
    smooth_params,
)
from eva_engine.body.kinematics import axis_angle_to_matrix
from eva_engine.body.params import BodyParams


def _params(t: int, joints: int = 4, expressions: int = 3) -> BodyParams:
    z = torch.zeros
    return BodyParams(z(t, 3), z(t, 3), z(t, joints, 3), z(t, expressions), torch.full((t, 2), 0.5))


def test_axis_angle_quaternion_round_trip_including_degenerate_angles():
    g = torch.Generator().manual_seed(0)
    axes = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    angles = torch.cat([torch.tensor([0.0, 1e-9, 1e-5, math.pi - 1e-6]), torch.rand(60, generator=g) * 3.1])
    rotvec = axes * angles.double()[:, None]
    back = quat_to_axis_angle(axis_angle_to_quat(rotvec))
    assert torch.allclose(axis_angle_to_matrix(back), axis_angle_to_matrix(rotvec), atol=1e-9)
    assert torch.isfinite(back).all()
    q = axis_angle_to_quat(rotvec)
    assert torch.allclose(q.norm(dim=-1), torch.ones(64, dtype=torch.float64))
    # q and -q are one rotation; the angle comes back in [0, pi].
    flipped = quat_to_axis_angle(-q)
    assert torch.allclose(axis_angle_to_matrix(flipped), axis_angle_to_matrix(rotvec), atol=1e-9)
    assert (quat_to_axis_angle(-q).norm(dim=-1) <= math.pi + 1e-9).all()


def test_continuous_quats_undo_sign_flips():
    q = axis_angle_to_quat(torch.tensor([[0.0, 0.0, a] for a in (0.1, 0.2, 0.3, 0.4)]))
    flipped = q * torch.tensor([1.0, -1.0, 1.0, -1.0])[:, None]
    assert torch.allclose(continuous_quats(flipped), q)


def test_smoothing_keeps_a_held_pose_and_calms_jitter():
    t = 30
    times = torch.arange(t, dtype=torch.float64) / 30.0
    held = _params(t)
    held.joints[:, 1] = torch.tensor([0.3, -1.2, 0.5])
    held.expression[:, 0] = 0.7
    out = smooth_params(held, times, sigma_s=0.05)
    assert torch.allclose(out.joints, held.joints, atol=1e-6)
    assert torch.allclose(out.expression, held.expression)
    # A jittering elbow angle: smoothing reduces the frame-to-frame change, keeps the mean.
    g = torch.Generator().manual_seed(1)
    jitter = _params(t)
    angle = 1.0 + 0.1 * torch.randn(t, generator=g)
    jitter.joints[:, 2, 1] = angle
    smooth = smooth_params(jitter, times, sigma_s=0.05).joints[:, 2, 1]
    assert smooth.diff().abs().mean() < 0.5 * angle.diff().abs().mean()
    assert abs(float(smooth.mean() - angle.mean())) < 0.02
    assert smooth_params(jitter, times, 0.0) is jitter
    with pytest.raises(ValueError, match="increasing"):
        smooth_params(jitter, times.flip(0), 0.05)


def test_resampling_interpolates_rotations_and_keeps_the_frames():
    p = _params(2)
    p.joints[1, 0] = torch.tensor([0.0, 0.0, 1.0])  # 1 rad about z
    p.transl[1] = torch.tensor([1.0, 0.0, 0.0])
    times = torch.tensor([0.0, 1.0], dtype=torch.float64)
    out = resample_params(p, times, torch.tensor([0.0, 0.25, 0.5, 1.0, 2.0], dtype=torch.float64))
    assert out.batch_size == 5
    assert torch.allclose(out.joints[2, 0], torch.tensor([0.0, 0.0, 0.5]), atol=1e-5)  # half the angle
    assert 0.2 < float(out.joints[1, 0, 2]) < 0.3
    assert torch.allclose(out.transl[:, 0], torch.tensor([0.0, 0.25, 0.5, 1.0, 1.0]))  # held after the end
    assert torch.allclose(resample_params(p, times, times).joints, p.joints, atol=1e-6)
    assert frame_times(0.0, 1.0, 10.0).shape == (11,) and frame_times(0.5, 0.5, 25.0).tolist() == [0.5]


def test_retarget_keeps_rotations_and_scales_the_root_about_the_camera(anny_model):
    body = anny_model
    tall, short = body.shape_defaults.clone(), body.shape_defaults.clone()
    height = body.shape_names.index("height")
    tall[height], short[height] = 0.9, 0.1
    assert body_height(body, tall) > body_height(body, short) + 0.1
    source = body.default_params(3)
    source.shape[:] = tall
    source.joints[:, 5] = torch.tensor([0.2, 0.1, -0.4])
    source.root_orient[:, 1] = 0.3
    source.expression[:, 0] = torch.tensor([0.2, 1.3, -0.1])  # outside [0, 1] is clamped
    source.transl[:] = torch.tensor([[0.1, 0.2, -3.0], [0.3, 0.1, -3.2], [0.0, 0.0, -2.8]])
    camera = torch.tensor([0.0, 0.0, 0.0])
    out = retarget(source, body, short, center=camera)
    assert torch.equal(out.joints, source.joints) and torch.equal(out.root_orient, source.root_orient)
    assert torch.allclose(out.shape, short.expand(3, -1))
    assert out.expression[:, 0].tolist() == pytest.approx([0.2, 1.0, 0.0])
    ratio = body_height(body, short) / body_height(body, tall)
    root_source = source.transl + rest_root(body, tall)
    root_target = out.transl + rest_root(body, short)
    assert torch.allclose(root_target - camera, ratio * (root_source - camera), atol=1e-5)
    # Seen from the camera, the root is where it was (a scene scaled about the camera's centre).
    direction = torch.nn.functional.normalize(root_target, dim=-1)
    assert torch.allclose(direction, torch.nn.functional.normalize(root_source, dim=-1), atol=1e-5)
    same = retarget(source, body, tall, center=camera)
    assert torch.allclose(same.transl, source.transl, atol=1e-5)
    moved = recenter(out)
    assert torch.allclose(moved.transl[0], torch.zeros(3)) and torch.allclose(
        moved.transl[1] - moved.transl[0], out.transl[1] - out.transl[0]
    )


def test_pose_sequences_from_json(anny_model):
    seq = driving_from_poses({"fps": 10, "poses": [{}, {"joints": {"upperarm01.L": [0, 0, -1]}}]}, anny_model)
    assert len(seq) == 2 and seq.fps == 10 and seq.times.tolist() == [0.0, 0.1]
    assert not seq.retarget and not seq.has_camera and seq.frames is None
    assert len(driving_from_poses([{}, {}, {}], anny_model)) == 3  # a bare list, 25 fps
    for doc, needle in (
        ({"poses": []}, "at least 1"),
        ({"poses": [{"joints": {"elbow_of_nobody": [0, 0, 1]}}]}, "elbow_of_nobody"),
        ({"poses": [{"joints": {"upperarm01.L": [0, 1]}}]}, "poses.0.joints"),
        ({"fps": 0, "poses": [{}]}, "fps"),
        ({"poses": [{}], "speed": 2}, "speed"),
        ("walk", "not a pose sequence"),
    ):
        with pytest.raises(DrivingError, match=needle):
            driving_from_poses(doc, anny_model)


def test_pose_controls_move_the_right_joints(anny_model):
    controls = pose_controls(anny_model)
    names = {c.name for c in controls}
    assert {
        "arm_out.L",
        "elbow.R",
        "fingers.L",
        "fingers.R",
        "head_turn",
        "jaw_open",
        "smile",
        "brows_up",
        "blink",
    } <= names
    assert all(c.min <= 0.0 <= c.max for c in controls)
    assert pose_from_controls(controls, {}).joints == {}
    params = anny_model.params_from_pose(pose_from_controls(controls, {"arm_out.L": 1.2, "smile": 0.5}))
    out = anny_model(params)
    rest = anny_model(anny_model.default_params(1))
    wrist = anny_model.joint_names.index("wrist.L")
    assert float(out.joints[0, wrist, 1] - rest.joints[0, wrist, 1]) > 0.2  # raising sideways lifts the hand
    smile = anny_model.expression_names.index("mouthSmileLeft")
    assert float(params.expression[0, smile]) == pytest.approx(0.5)
    # Curling the fingers brings the fingertips towards the wrist.
    curled = anny_model(anny_model.params_from_pose(pose_from_controls(controls, {"fingers.L": 1.0})))
    tip = anny_model.joint_names.index("finger3-3.L")
    reach = (curled.joints[0, tip] - curled.joints[0, wrist]).norm()
    assert reach < (rest.joints[0, tip] - rest.joints[0, wrist]).norm()
    with pytest.raises(ValueError, match="outside"):
        pose_from_controls(controls, {"jaw_open": 2.0})
    with pytest.raises(ValueError, match="unknown"):
        pose_from_controls(controls, {"wings": 1.0})


def test_the_budget_counts_the_frames_a_variable_frame_rate_will_render():
    """Ten driving frames whose timestamps span 100 s (a variable frame rate): the rendered
    animation has a frame per 1/fps of that span, and the job's budget counts those, not ten."""
    from eva_engine.animate.timing import frame_times
    from eva_engine.specs.animation import AnimationConfig, AnimationError, output_frames
    from jobs.animation import check_animation_budget

    times = torch.tensor([0.0, 0.1, 0.2, 0.3, 0.4, 50.0, 99.6, 99.7, 99.8, 100.0], dtype=torch.float64)
    config = AnimationConfig(width=64, height=64)
    rendered = len(frame_times(float(times[0]), float(times[-1]), 10.0))
    assert rendered == 1001 == output_frames(10, 10.0, config, span_s=float(times[-1] - times[0]))
    assert output_frames(10, 10.0, config) == 10  # the nominal count the upload could make
    budget = 100 * 64 * 64
    check_animation_budget(config, 10, 10.0, None, budget)
    with pytest.raises(AnimationError, match="1001 frames"):
        check_animation_budget(config, 10, 10.0, None, budget, span_s=100.0)
