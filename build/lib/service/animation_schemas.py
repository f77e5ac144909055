"""The API's contract for animations and posing: what ``POST /avatars/{id}/animations`` answers,
an animation's state, and the pose controls (sliders) of an avatar."""

from __future__ import annotations

import json
from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, computed_field, field_validator

from eva_engine.animate.controls import PoseControl
from eva_engine.specs.camera import CameraSpec
from jobs.animation import AnimationOptions, AnimationRequest
from jobs.store import JobRecord
from service.schemas import JobCreated, JobState, job_progress, utc_time


class AnimationForm(AnimationRequest):
    """The form fields of ``POST /avatars/{id}/animations`` beside the upload: ``AnimationRequest``,
    its names, defaults and bounds, with ``camera`` also a ``CameraSpec`` as JSON text. Other
    fields are ignored (the upload is one of them)."""

    model_config = ConfigDict(extra="ignore")

    camera: Literal["driving"] | CameraSpec = Field(
        "front",
        validate_default=True,
        description="A preset (front, left, ...), 'driving' (the video's "
        "own camera) or a CameraSpec as JSON; an orbit without target/distance is framed on the avatar.",
    )

    @field_validator("camera", mode="before")
    @classmethod
    def _json_text(cls, value):
        if not isinstance(value, str):
            return value
        text = value.strip()
        if not text.startswith("{"):
            return text
        try:
            return json.loads(text)
        except ValueError as err:
            raise ValueError(f"camera is not a preset name, 'driving' or valid JSON: {err}") from err


class AnimationCreated(JobCreated):
    """The job that makes the animation; ``animation_url`` has its state, then its video."""

    animation_id: str = Field(examples=["5e4d3c2b1a0f9e8d7c6b5a4f3e2d1c0b"])

    @computed_field(examples=["/animations/5e4d3c2b1a0f9e8d7c6b5a4f3e2d1c0b"])
    @property
    def animation_url(self) -> str:
        return f"/animations/{self.animation_id}"


class AnimationInfo(BaseModel):
    """An animation: its job's state and progress (0..1 over preprocess, align, render, export);
    once ``succeeded``, ``video_url`` serves the mp4 and the video's facts are filled in."""

    animation_id: str
    avatar_id: str = Field(description="The avatar animated.")
    job_id: str
    state: JobState
    stage: Literal["preprocess", "align", "render", "export"] | None
    progress: float
    eta_seconds: float | None
    message: str | None
    error: str | None
    source: str | None = Field(None, description="The uploaded file's name.")
    options: AnimationOptions
    created_at: datetime
    finished_at: datetime | None
    video_url: str | None = Field(None, description="The mp4 (H.264), once succeeded.")
    frames: int | None = None
    fps: float | None = None
    width: int | None = None
    height: int | None = None
    duration_s: float | None = None
    driving_frames_without_person: int | None = Field(
        None, description="Frames of the driving video where nobody was found (skipped, interpolated)."
    )

    @classmethod
    def of(cls, job: JobRecord, info: dict | None = None) -> AnimationInfo:
        """From the job record and, once published, the animation's ``animation.json``."""
        info = info or {}
        done = job.state == "succeeded" and bool(info)
        return cls(
            animation_id=job.output_id,
            avatar_id=job.options["avatar_id"],
            job_id=job.id,
            **job_progress(job),
            source=job.filename,
            options=AnimationOptions.model_validate(job.options),
            created_at=utc_time(job.created_at),
            finished_at=utc_time(job.finished_at),
            video_url=f"/animations/{job.output_id}/video" if done else None,
            **{
                k: info.get(k)
                for k in ("frames", "fps", "width", "height", "duration_s", "driving_frames_without_person")
            },
        )  # type: ignore[arg-type]


class AnimationList(BaseModel):
    animations: list[AnimationInfo]


class Framing(BaseModel):
    """An orbit camera that fits the avatar (``CameraSpec`` fields)."""

    target: tuple[float, float, float]
    distance: float
    fov_y: float


class PoseControls(BaseModel):
    """Sliders for posing an avatar (see ``eva_engine.animate.controls``): a joint's rotation is
    the product, in list order, of its controls' ``exp(value * gain * axis)`` (axis-angle in the
    pose JSON); an expression is the sum of ``value * gain``. ``framing``: an orbit camera that
    fits the avatar."""

    body_model: str
    controls: list[PoseControl]
    framing: Framing
