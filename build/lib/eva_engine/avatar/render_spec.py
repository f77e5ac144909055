"""``RenderSpec``: one still of an avatar as JSON -- a pose (or a training frame), a camera, an
image size and a background. The render endpoint's body and ``eva render``'s options are this
schema, so both validate a pose and a camera the same way, within the same physical bounds
(``RenderPose``, ``CameraSpec``).

    spec = RenderSpec.model_validate({"pose": {...}, "camera": "left", "width": 256, "height": 256})
    image = render_spec(avatar, spec, load_avatar_frames(folder))   # [H, W, 3] uint8

A request outside what the training frames showed still renders; ``coverage_warnings`` says what
lies outside (``avatar.coverage``).
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
import torch
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)

from eva_engine.avatar.coverage import Coverage, rest_root
from eva_engine.avatar.frames import AvatarFrames
from eva_engine.avatar.model import Avatar
from eva_engine.body.kinematics import axis_angle_to_matrix
from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams, BodyPose
from eva_engine.render.camera import Camera
from eva_engine.render.view import camera_from_spec
from eva_engine.specs.camera import (
    CAMERA_PRESETS,
    DEFAULT_SIZE,
    MAX_FRAME_INDEX,
    CameraSpec,
    Position,
    camera_preset,
)

# Physical bounds of what a pose may ask for (the camera's are in ``eva_engine.specs.camera``):
# finite is not enough (1e300 becomes inf in float32 and renders a blank image), and a bounded
# request has a bounded cost.
MAX_POSE_KEYS = 256
MAX_ROTATION = 2.0 * math.pi  # radians: every rotation has an axis-angle of norm <= pi
EXPRESSION_RANGE = 3.0  # SMPL-X's coefficients are standard deviations; Anny's [0, 1] is the model's own
SHAPE_RANGE = 5.0
MAX_SIDE = 4096


def _rotation(value: tuple[float, float, float]) -> tuple[float, float, float]:
    if math.hypot(*value) > MAX_ROTATION:
        raise ValueError(
            f"an axis-angle rotation must have a norm of at most 2 pi ({MAX_ROTATION:.4f}) radians"
        )
    return value


Name = Annotated[str, StringConstraints(min_length=1, max_length=64)]
Angle = Annotated[float, Field(ge=-MAX_ROTATION, le=MAX_ROTATION)]
AxisAngle = Annotated[tuple[Angle, Angle, Angle], AfterValidator(_rotation)]
Unit = Annotated[float, Field(ge=0.0, le=1.0)]


class RenderInputError(ValueError):
    """A render that names something the avatar does not have (a training frame out of range), or
    values outside its body model's own range."""


class RenderPose(BodyPose):
    """``BodyPose`` with the bounds a render (the API's, ``eva render``'s, a JSON motion's frame)
    must keep: at most 256 names per dict (of at most 64 characters), axis-angles of norm <= 2 pi,
    translation within 10 m, expression within +-3 and shape within +-5 (and within the body
    model's own range: ``check_pose_ranges``)."""

    joints: dict[Name, AxisAngle] = Field(
        default_factory=dict,
        max_length=MAX_POSE_KEYS,
        description="Axis-angle [rx, ry, rz] (radians) per joint name.",
    )
    root_orient: AxisAngle = Field((0.0, 0.0, 0.0), description="Root axis-angle (radians), world axes.")
    transl: Position = Field((0.0, 0.0, 0.0), description="Root translation in metres, world axes.")
    expression: dict[Name, Annotated[float, Field(ge=-EXPRESSION_RANGE, le=EXPRESSION_RANGE)]] = Field(
        default_factory=dict, max_length=MAX_POSE_KEYS, description="Facial expression coefficient per name."
    )
    shape: dict[Name, Annotated[float, Field(ge=-SHAPE_RANGE, le=SHAPE_RANGE)]] = Field(
        default_factory=dict, max_length=MAX_POSE_KEYS, description="Shape parameter per name."
    )


def check_pose_ranges(body: BodyModel, pose: BodyPose) -> None:
    """``RenderInputError`` when ``pose``'s expression or shape values fall outside ``body``'s own
    ranges (e.g. Anny's expressions and phenotypes in [0, 1])."""
    for kind, values, bounds in (
        ("expression", pose.expression, body.expression_bounds),
        ("shape", pose.shape, body.shape_bounds),
    ):
        if bounds is None:
            continue
        lo, hi = bounds
        outside = [name for name, v in values.items() if not lo <= v <= hi]
        if outside:
            raise RenderInputError(
                f"{kind} value(s) of {outside[:8]} outside the {body.name} model's range [{lo}, {hi}]"
            )


class RenderSpec(BaseModel):
    """Every key is optional: the default is the rest pose seen from the front, 512x512 on white.

    ``frame`` renders training frame ``i`` with its fitted pose (and, unless ``camera`` is given,
    its camera and image size) to compare with the input video.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    pose: RenderPose | None = Field(None, description="Body pose JSON (see BodyPose); default: rest pose.")
    frame: int | None = Field(
        None, ge=0, le=MAX_FRAME_INDEX, description="Render training frame i (its fitted pose)."
    )
    camera: CameraSpec | None = Field(
        None, description=f"Orbit or K/viewmat, or a preset name: {list(CAMERA_PRESETS)}."
    )
    width: int | None = Field(None, ge=16, le=MAX_SIDE, description="Pixels (default 512, or the frame's).")
    height: int | None = Field(None, ge=16, le=MAX_SIDE, description="Pixels (default 512, or the frame's).")
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


def uses_training_frame(spec: RenderSpec) -> bool:
    """Whether ``spec`` reads a training frame (its pose or its camera), and so takes its default
    size from it."""
    return spec.frame is not None or (spec.camera is not None and spec.camera.frame is not None)


def resolve_size(spec: RenderSpec, frames: AvatarFrames | tuple[int, int] | None) -> tuple[int, int]:
    """(width, height): as asked, else the training frame's (for ``frame`` or a frame's camera; one
    side given keeps the frame's aspect), else ``DEFAULT_SIZE``. ``frames``: the avatar's training
    frames, or just their (height, width) (e.g. from ``AvatarMeta.frames``, without loading
    them)."""
    size = frames.image_size if isinstance(frames, AvatarFrames) else frames
    if uses_training_frame(spec) and size is not None and size[0] > 0 and size[1] > 0:
        h, w = size
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
    Raises ``InvalidPoseError`` for names the avatar's body model does not have and
    ``RenderInputError`` for values outside its ranges."""
    if spec.frame is not None:
        return frame_params(frames, spec.frame)
    pose = spec.pose or RenderPose()
    check_pose_ranges(avatar.body, pose)
    return avatar.body.params_from_pose(pose)


def spec_camera(
    spec: RenderSpec,
    width: int,
    height: int,
    frames: AvatarFrames | None,
    avatar: Avatar | None = None,
    params: BodyParams | None = None,
) -> Camera:
    """The camera ``spec`` asks for; a training frame without ``camera`` uses that frame's own
    camera, with K scaled to the requested size. A frame's camera (``camera.frame``) needs the
    ``avatar`` and the ``params`` rendered (``frame_camera``)."""
    if spec.camera is None and spec.frame is not None and frames is not None and spec.frame < len(frames):
        return Camera(
            _scaled_K(frames, spec.frame, width, height), frames.viewmat[spec.frame].float(), width, height
        )
    if spec.camera is not None and spec.camera.frame is not None:
        if avatar is None or params is None:
            raise ValueError("a training frame's camera needs the avatar and the params rendered")
        cam = spec.camera
        return frame_camera(
            avatar, frames, cam.frame, params, cam.yaw or 0.0, cam.pitch or 0.0, width, height
        )
    return camera_from_spec(spec.camera, width, height)


def _scaled_K(frames: AvatarFrames, index: int, width: int, height: int) -> torch.Tensor:
    h0, w0 = frames.image_size
    K = frames.K[index].clone().float()
    if h0 > 0 and w0 > 0:
        K[0] *= width / w0
        K[1] *= height / h0
    return K


def _body_to_world(params: BodyParams, root: torch.Tensor) -> torch.Tensor:
    """[4, 4] float64: the body's root frame (its root rotation about its rest root position, then
    ``transl``) into the world, for ``params`` with batch 1."""
    rot = axis_angle_to_matrix(params.root_orient[0].detach().double())
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rot
    out[:3, 3] = params.transl[0].detach().double() + root.double()
    return out


def _turn(yaw_deg: float, pitch_deg: float) -> torch.Tensor:
    """[4, 4] float64: raise by ``pitch_deg`` (about the body's x axis), then turn by ``yaw_deg``
    about its up axis (positive: toward the subject's left, as ``orbit_camera``)."""
    up = axis_angle_to_matrix(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
    raise_ = axis_angle_to_matrix(torch.tensor([-math.radians(pitch_deg), 0.0, 0.0], dtype=torch.float64))
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = up @ raise_
    return out


def frame_camera(
    avatar: Avatar,
    frames: AvatarFrames | None,
    index: int,
    params: BodyParams,
    yaw_deg: float,
    pitch_deg: float,
    width: int,
    height: int,
) -> Camera:
    """Training frame ``index``'s camera placed where it was relative to the body in that frame,
    for a body posed by ``params`` (batch 1), then turned by ``yaw_deg`` and ``pitch_deg`` about
    the body's root: a new pose is framed the way the video framed the person."""
    if frames is None:
        raise RenderInputError("this avatar keeps no training frames, so no frame's camera")
    if index >= len(frames):
        raise RenderInputError(
            f"camera frame {index} is out of range: the avatar has {len(frames)} training frames"
        )
    root = rest_root(avatar.body, avatar.shape[None])
    to_camera = frames.viewmat[index].double() @ _body_to_world(frames.params[index], root)  # body -> camera
    view = (
        to_camera
        @ torch.linalg.inv(_turn(yaw_deg, pitch_deg))
        @ torch.linalg.inv(_body_to_world(params, root))
    )
    view[3] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    return Camera(_scaled_K(frames, index, width, height), view.float(), width, height)


def coverage_warnings(
    coverage: Coverage | None, avatar: Avatar, spec: RenderSpec, params: BodyParams, camera: Camera
) -> list[str]:
    """What the render of ``spec`` (its ``params`` and ``camera``) asks for beyond what the avatar's
    training frames showed (``Coverage.warnings``); none for a training frame through its own
    camera, or an avatar that recorded no coverage."""
    if coverage is None or (spec.frame is not None and spec.camera is None):
        return []
    return coverage.warnings(avatar.body, params, camera.viewmat)


def render_image(avatar: Avatar, params: BodyParams, camera: Camera, background) -> np.ndarray:
    """[H, W, 3] uint8 image of ``avatar`` in ``params`` (batch 1) through ``camera``."""
    with torch.no_grad():
        image = avatar.render(params, camera, torch.tensor(background, dtype=torch.float32))
    return (image.cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def render_spec(avatar: Avatar, spec: RenderSpec, frames: AvatarFrames | None = None) -> np.ndarray:
    """[H, W, 3] uint8: the still ``spec`` describes (no size limit is applied here)."""
    width, height = resolve_size(spec, frames)
    params = spec_params(avatar, spec, frames)
    return render_image(
        avatar, params, spec_camera(spec, width, height, frames, avatar, params), spec.background
    )
