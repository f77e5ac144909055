"""``AnimationConfig``: how an animation is rendered (the options of ``eva animate`` and of the
animation endpoint), and what it costs before anything is rendered (``output_size``,
``output_frames``). Torch-free: the job queue validates and budgets animation jobs with it."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from eva_engine.specs.camera import DEFAULT_SIZE, CameraSpec, camera_preset

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
