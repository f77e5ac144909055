"""A render request's camera: a training frame's camera (``{"camera": {"frame": i}}``) stays where
it was relative to the body, so a new pose is framed as the video framed the person, and its
yaw and pitch turn it about the body; clear errors for what it cannot be combined with."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.scenes import front_camera, random_params, teacher_avatar
from pydantic import ValidationError

from eva_engine.avatar import AvatarFrames
from eva_engine.avatar.coverage import rest_root, view_angles
from eva_engine.avatar.render_spec import RenderInputError, RenderSpec, render_spec, spec_camera, spec_params


@pytest.fixture(scope="module")
def scene(anny_model):
    avatar = teacher_avatar(anny_model, n=1500)
    cam = front_camera(64)
    params = random_params(anny_model, 3, seed=4)
    params.transl[1] = torch.tensor([0.2, -0.1, 0.3])  # the person walked and turned in frame 1
    params.root_orient[1] = torch.tensor([0.0, 0.6, 0.0])
    frames = AvatarFrames(
        params=params,
        K=cam.K.expand(3, 3, 3),
        viewmat=cam.viewmat.expand(3, 4, 4),
        timestamps=torch.zeros(3, dtype=torch.float64),
        image_size=(64, 64),
        fps=10.0,
    )
    return avatar, frames


def _pose_json(model, params, i: int) -> dict:
    return model.pose_from_params(params, i, sparse=False).model_dump()


def test_a_frames_camera_on_that_frames_pose_is_the_frame(scene, anny_model):
    avatar, frames = scene
    own = render_spec(avatar, RenderSpec(frame=1), frames)
    again = render_spec(
        avatar, RenderSpec(pose=_pose_json(anny_model, frames.params, 1), camera={"frame": 1}), frames
    )
    assert own.shape == again.shape == (64, 64, 3)
    assert np.abs(own.astype(int) - again.astype(int)).max() <= 2


def test_a_frames_camera_follows_the_body(scene, anny_model):
    """The same joints placed elsewhere in the world (the rest root) look the same through frame
    1's camera as in frame 1: the camera keeps its place relative to the body."""
    avatar, frames = scene
    pose = _pose_json(anny_model, frames.params, 1)
    moved = {**pose, "root_orient": (0.0, 0.0, 0.0), "transl": (0.0, 0.0, 0.0)}
    image = render_spec(avatar, RenderSpec(pose=moved, camera={"frame": 1}), frames)
    own = render_spec(avatar, RenderSpec(frame=1), frames)
    assert np.abs(image.astype(int) - own.astype(int)).mean() < 1.0
    # Turned 35 deg about the body: the camera's yaw about the body moves by 35 deg.
    spec = RenderSpec(pose=moved, camera={"frame": 1, "yaw": 35.0, "pitch": 10.0})
    params = spec_params(avatar, spec, frames)
    turned = spec_camera(spec, 64, 64, frames, avatar, params)
    root = rest_root(anny_model, avatar.shape[None])
    yaw0, pitch0 = view_angles(frames.params[[1]], frames.viewmat[1], root)
    yaw, pitch = view_angles(params, turned.viewmat, root)
    assert float(yaw[0] - yaw0[0]) == pytest.approx(35.0, abs=1.5)
    assert float(pitch[0]) > float(pitch0[0]) + 5.0
    assert torch.allclose(turned.K, frames.K[1])  # same lens and framing
    assert not np.array_equal(render_spec(avatar, spec, frames), image)


def test_a_frames_camera_needs_frames_and_nothing_else(scene):
    avatar, frames = scene
    with pytest.raises(ValidationError, match="cannot be combined with 'frame'"):
        RenderSpec(camera={"frame": 0, "distance": 2.0})
    with pytest.raises(RenderInputError, match="out of range"):
        render_spec(avatar, RenderSpec(camera={"frame": 7}), frames)
    with pytest.raises(RenderInputError, match="no training frames"):
        render_spec(avatar, RenderSpec(camera={"frame": 0}), None)
    # The frame's size is the default, as for a training frame's own render.
    assert render_spec(avatar, RenderSpec(camera={"frame": 0}, width=32), frames).shape == (32, 32, 3)
