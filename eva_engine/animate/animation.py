"""An avatar performing a driving sequence, rendered frame by frame and encoded as an H.264 mp4.

    driving = load_driving("someone_signing.mp4", avatar.body)
    result = animate(avatar, driving, AnimationConfig(camera="front", side_by_side=True))
    write_animation("out.mp4", result)

Steps: retarget the motion onto the avatar (``retarget``: rotations and expressions carry over,
the avatar keeps its shape, the root's position scales with the height ratio), smooth it over
time (``smooth_s``), resample it at the output frame rate, then render each frame -- through the
driving video's camera (``camera="driving"``: the avatar where the person was) or a fixed orbit
camera framed on the avatar -- optionally beside the driving frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator

from eva_engine.animate.driving import DrivingSequence
from eva_engine.animate.retarget import recenter, retarget
from eva_engine.animate.timing import frame_times, resample_params, smooth_params
from eva_engine.avatar.framing import framed_camera
from eva_engine.avatar.model import Avatar
from eva_engine.avatar.render_spec import render_image
from eva_engine.body.params import BodyParams
from eva_engine.progress import Progress, ProgressEvent
from eva_engine.render.camera import Camera
from eva_engine.render.view import DEFAULT_SIZE, CameraSpec, camera_from_spec, camera_preset

Unit = Annotated[float, Field(ge=0.0, le=1.0)]
MAX_SIDE = 4096


class AnimationError(ValueError):
    """Options that do not fit the driving sequence (e.g. its camera asked of a JSON motion)."""


class AnimationConfig(BaseModel):
    """How an animation is rendered (the options of ``eva animate`` and of the animation endpoint).

    camera: ``"driving"`` (the driving video's own camera and image size), a preset name
    (``front``, ``left``, ...) or an orbit/matrix ``CameraSpec``; an orbit without ``target`` /
    ``distance`` is framed on the avatar. width / height: output pixels of the avatar's picture
    (default: the driving frame's size for ``driving``, else square at the driving frame's height
    or 512). side_by_side: the driving frame on the left, the avatar on the right (videos only).
    fps: output frame rate (default the driving sequence's), the motion resampled in time.
    smooth_s: standard deviation in seconds of the temporal smoothing (0: none). background: RGB
    in [0, 1].
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    camera: Literal["driving"] | CameraSpec = Field(
        CameraSpec(), description="'driving' (the driving video's camera), a preset name or a CameraSpec."
    )
    width: int | None = Field(None, ge=16, le=MAX_SIDE)
    height: int | None = Field(None, ge=16, le=MAX_SIDE)
    side_by_side: bool = False
    fps: float | None = Field(None, gt=0.0, le=120.0)
    smooth_s: float = Field(0.04, ge=0.0, le=2.0)
    background: tuple[Unit, Unit, Unit] = (1.0, 1.0, 1.0)

    @field_validator("camera", mode="before")
    @classmethod
    def _preset(cls, value):
        return value if value == "driving" else camera_preset(value)

    @field_validator("camera")
    @classmethod
    def _not_a_frames(cls, value):
        if isinstance(value, CameraSpec) and value.frame is not None:
            raise ValueError(
                "a training frame's camera is for a still render; animate with 'driving' or an orbit"
            )
        return value


@dataclass
class Animation:
    """frames: uint8 [N, H, W, 3]; fps; times: [N] seconds of the driving sequence each frame
    shows; params: BodyParams [N], the avatar's motion (retargeted, smoothed, resampled)."""

    frames: np.ndarray
    fps: float
    times: torch.Tensor
    params: BodyParams

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def avatar_motion(
    avatar: Avatar, driving: DrivingSequence, config: AnimationConfig
) -> tuple[BodyParams, torch.Tensor]:
    """The avatar's motion [N] at the output frames' times [N] (seconds): retargeted (videos),
    moved to the orbit's origin (orbit cameras), smoothed and resampled at ``config.fps``."""
    params = driving.params.to(dtype=avatar.shape.dtype)
    own_camera = config.camera == "driving"
    if driving.retarget:
        center = driving.viewmat[0].inverse()[:3, 3] if driving.has_camera else None
        params = retarget(params, avatar.body, avatar.shape, center=center)
        if not own_camera:
            params = recenter(params)
    params = smooth_params(params, driving.times, config.smooth_s)
    fps = config.fps or driving.fps
    times = frame_times(float(driving.times[0]), float(driving.times[-1]), fps)
    return resample_params(params, driving.times, times), times


def _nearest(driving: DrivingSequence, times: torch.Tensor) -> torch.Tensor:
    """Index [N] of the driving frame nearest each of ``times``."""
    return (times[:, None] - driving.times[None, :]).abs().argmin(dim=1)


def output_size(config: AnimationConfig, image_size: tuple[int, int] | None) -> tuple[int, int]:
    """(width, height) of the avatar's picture for driving frames of ``image_size`` (height,
    width; None for a pose sequence, which has no frames)."""
    if config.camera == "driving" and image_size is not None:
        h0, w0 = image_size
        if config.width and not config.height:
            return config.width, max(16, round(config.width * h0 / w0))
        if config.height and not config.width:
            return max(16, round(config.height * w0 / h0)), config.height
        return config.width or w0, config.height or h0
    side = image_size[0] if image_size else DEFAULT_SIZE
    return config.width or config.height or side, config.height or config.width or side


def output_frames(frames: int, fps: float, config: AnimationConfig, span_s: float | None = None) -> int:
    """Frames of the animation of ``frames`` driving frames at ``fps`` (resampled at
    ``config.fps``), as ``avatar_motion`` renders them: over the driving frames' real time span
    ``span_s`` when it is known (a variable frame rate can stretch it far past ``frames / fps``),
    else over ``(frames - 1) / fps``."""
    span = span_s if span_s is not None else max(frames - 1, 0) / fps
    return int(span * (config.fps or fps) + 1e-6) + 1


def _size(driving: DrivingSequence, config: AnimationConfig) -> tuple[int, int]:
    """(width, height) of the avatar's picture."""
    return output_size(config, driving.image_size)


def _resize(frame: np.ndarray, height: int) -> np.ndarray:
    from PIL import Image

    h, w = frame.shape[:2]
    width = max(1, round(w * height / h))
    return np.asarray(Image.fromarray(frame).resize((width, height), Image.BILINEAR))


def animate(
    avatar: Avatar,
    driving: DrivingSequence,
    config: AnimationConfig | None = None,
    progress: Progress | None = None,
) -> Animation:
    """Render ``avatar`` performing ``driving`` (see the module docstring; ``progress`` hears
    stage "render", frame by frame). Raises ``AnimationError`` when the options need what the
    sequence lacks (its camera, its frames)."""
    config = config or AnimationConfig()
    if len(driving) == 0:
        raise AnimationError("the driving sequence has no frames")
    if config.camera == "driving" and not driving.has_camera:
        raise AnimationError("camera 'driving' needs a driving video; a pose sequence has no camera")
    if config.side_by_side and driving.frames is None:
        raise AnimationError("side by side needs a driving video; a pose sequence has no frames")
    params, times = avatar_motion(avatar, driving, config)
    width, height = _size(driving, config)
    nearest = _nearest(driving, times)
    fixed = None
    if config.camera != "driving":
        fixed = camera_from_spec(framed_camera(avatar, config.camera, width, height), width, height)
    frames = []
    started = time.perf_counter()
    for i in range(len(times)):
        if fixed is None:
            j = int(nearest[i])
            h0, w0 = driving.image_size  # type: ignore[misc]
            K = driving.K[j].clone()
            K[0] *= width / w0
            K[1] *= height / h0
            camera = Camera(K, driving.viewmat[j], width, height)
        else:
            camera = fixed
        image = render_image(avatar, params[i], camera, config.background)
        if config.side_by_side:
            image = np.concatenate([_resize(driving.frames[int(nearest[i])], height), image], axis=1)
        frames.append(image)
        if progress is not None:
            done, elapsed = i + 1, time.perf_counter() - started
            progress(
                ProgressEvent(
                    "render",
                    done,
                    len(times),
                    f"rendering frame {done}/{len(times)}",
                    elapsed=elapsed,
                    eta=elapsed / done * (len(times) - done),
                )
            )
    return Animation(np.stack(frames), float(config.fps or driving.fps), times, params)


def write_animation(path: str | Path, animation: Animation, quality: int = 18) -> Path:
    """Encode ``animation`` as H.264 (``.mp4``; PyAV, constant quality ``quality``)."""
    from eva_engine.data import write_video

    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"an animation is written as .mp4, got {path.name}")
    return write_video(path, animation.frames, fps=animation.fps, quality=quality)
