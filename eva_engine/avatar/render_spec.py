"""``RenderSpec``: one still of an avatar as JSON -- a pose (or a training frame), a camera, an
image size and a background. The render endpoint's body and ``eva render``'s options are this
schema, so both validate a pose and a camera the same way.

    spec = RenderSpec.model_validate({"pose": {...}, "camera": "left", "width": 256, "height": 256})
    image = render_spec(avatar, spec, load_avatar_frames(folder))   # [H, W, 3] uint8
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from eva_engine.avatar.frames import AvatarFrames
from eva_engine.avatar.model import Avatar
from eva_engine.body.params import BodyParams, BodyPose
from eva_engine.render.camera import Camera
from eva_engine.render.view import CAMERA_PRESETS, DEFAULT_SIZE, CameraSpec, camera_from_spec, camera_preset

Unit = Annotated[float, Field(ge=0.0, le=1.0)]


class RenderInputError(ValueError):
    """A render that names something the avatar does not have (a training frame out of range)."""


class RenderSpec(BaseModel):
    """Every key is optional: the default is the rest pose seen from the front, 512x512 on white.

    ``frame`` renders training frame ``i`` with its fitted pose (and, unless ``camera`` is given,
    its camera and image size) to compare with the input video.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    pose: BodyPose | None = Field(None, description="Body pose JSON (see BodyPose); default: rest pose.")
    frame: int | None = Field(None, ge=0, description="Render training frame i (its fitted pose).")
    camera: CameraSpec | None = Field(
        None, description=f"Orbit or K/viewmat, or a preset name: {list(CAMERA_PRESETS)}."
    )
    width: int | None = Field(None, ge=16, description="Pixels (default 512, or the frame's).")
    height: int | None = Field(None, ge=16, description="Pixels (default 512, or the frame's).")
    background: tuple[Unit, Unit, Unit] = Field((1.0, 1.0, 1.0), description="RGB in [0, 1].")

    @field_validator("camera", mode="before")
    @classmethod
    def _preset(cls, value):
        return camera_preset(value)

    @model_validator(mode="after")
    def _pose_or_frame(self) -> RenderSpec:
        if self.pose is not None and self.frame is not None:
            raise ValueError("give 'pose' or 'frame', not both")
        return self


def resolve_size(spec: RenderSpec, frames: AvatarFrames | None) -> tuple[int, int]:
    """(width, height): as asked, else the training frame's (for ``frame``; one side given keeps
    the frame's aspect), else ``DEFAULT_SIZE``."""
    if spec.frame is not None and frames is not None and frames.size[0] > 0:
        h, w = frames.size
        if spec.width is not None and spec.height is None:
            return spec.width, max(16, round(spec.width * h / w))
        if spec.height is not None and spec.width is None:
            return max(16, round(spec.height * w / h)), spec.height
        return spec.width or w, spec.height or h
    return spec.width or DEFAULT_SIZE, spec.height or DEFAULT_SIZE


def frame_params(frames: AvatarFrames | None, index: int) -> BodyParams:
    """Training frame ``index``'s params (batch 1); ``RenderInputError`` if there is no such frame."""
    if frames is None:
        raise RenderInputError("this avatar keeps no training frames")
    if index >= len(frames):
        raise RenderInputError(f"frame {index} is out of range: the avatar has {len(frames)} training frames")
    return frames.params[index]


def spec_params(avatar: Avatar, spec: RenderSpec, frames: AvatarFrames | None) -> BodyParams:
    """The body parameters (batch 1) ``spec`` asks for: its pose, training frame or the rest pose.
    Raises ``InvalidPoseError`` for names the avatar's body model does not have."""
    if spec.frame is not None:
        return frame_params(frames, spec.frame)
    return avatar.body.params_from_pose(spec.pose or BodyPose())


def spec_camera(spec: RenderSpec, width: int, height: int, frames: AvatarFrames | None) -> Camera:
    """The camera ``spec`` asks for; a training frame without ``camera`` uses that frame's own
    camera, with K scaled to the requested size."""
    if spec.camera is None and spec.frame is not None and frames is not None and spec.frame < len(frames):
        h0, w0 = frames.size
        K = frames.K[spec.frame].clone().float()
        if h0 > 0 and w0 > 0:
            K[0] *= width / w0
            K[1] *= height / h0
        return Camera(K, frames.viewmat[spec.frame].float(), width, height)
    return camera_from_spec(spec.camera, width, height)


def render_image(avatar: Avatar, params: BodyParams, camera: Camera, background) -> np.ndarray:
    """[H, W, 3] uint8 image of ``avatar`` in ``params`` (batch 1) through ``camera``."""
    with torch.no_grad():
        image = avatar.render(params, camera, torch.tensor(background, dtype=torch.float32))
    return (image.cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def render_spec(avatar: Avatar, spec: RenderSpec, frames: AvatarFrames | None = None) -> np.ndarray:
    """[H, W, 3] uint8: the still ``spec`` describes (no size limit is applied here)."""
    width, height = resolve_size(spec, frames)
    params = spec_params(avatar, spec, frames)
    return render_image(avatar, params, spec_camera(spec, width, height, frames), spec.background)
