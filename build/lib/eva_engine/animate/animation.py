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

import numpy as np
import torch

from eva_engine.animate.driving import DrivingSequence
from eva_engine.animate.retarget import recenter, retarget
from eva_engine.animate.timing import frame_times, resample_params, smooth_params
from eva_engine.avatar.framing import framed_camera
from eva_engine.avatar.model import Avatar
from eva_engine.avatar.render_spec import render_image
from eva_engine.body.params import BodyParams
from eva_engine.data import write_video
from eva_engine.progress import Progress, ProgressEvent
from eva_engine.render.camera import Camera
from eva_engine.render.view import camera_from_spec
from eva_engine.specs.animation import AnimationConfig, AnimationError, output_size


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
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"an animation is written as .mp4, got {path.name}")
    return write_video(path, animation.frames, fps=animation.fps, quality=quality)
