"""The API's contract: request and response models (with the examples shown at ``/docs``)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, computed_field

from eva_engine.avatar.render_spec import (  # noqa: F401  (the bounds, re-exported for clients)
    MAX_FRAME_INDEX,
    MAX_POSE_KEYS,
    MAX_SIDE,
    RenderPose,
    RenderSpec,
)
from eva_engine.eval.quality import QualityReport
from eva_engine.specs.camera import CAMERA_PRESETS, CameraSpec  # noqa: F401
from jobs.animation import AnimationOptions
from jobs.kinds import KIND_MODULES, job_kind, job_kinds
from jobs.options import JobOptions
from jobs.store import JobRecord

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
# From the registry, so a new kind's name and stages reach the API's schema.
JobKindName = Literal[tuple(KIND_MODULES)]  # type: ignore[valid-type]
JobStage = Literal[tuple(dict.fromkeys(s for kind in job_kinds().values() for s in kind.stages))]  # type: ignore[valid-type]
AvatarStatus = Literal["pending", "ready", "failed", "cancelled"]


def utc_time(ts: float | None) -> datetime | None:
    """A store's Unix seconds as an aware UTC datetime (None stays None)."""
    return datetime.fromtimestamp(ts, UTC) if ts is not None else None


class ErrorMessage(BaseModel):
    detail: str = Field(examples=["no avatar with id 0123456789abcdef0123456789abcdef"])


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    version: str
    queue: str = Field(description="sqlite or redis")
    records: str = Field("sqlite", description="Where the job records are: sqlite or redis.")
    storage: str = Field("disk", description="Where avatars and uploads are: disk or s3.")
    jobs: dict[str, int] = Field(description="Job count per state.")
    jobs_age_s: float = Field(
        0.0, description="How old those counts are, s (under 1 unless the job store is slow)."
    )
    renders: dict[str, int] = Field(default_factory=dict, description="Renders running and waiting.")


class AvatarForm(JobOptions):
    """The form fields of ``POST /avatars`` beside the video: ``JobOptions``, its names, defaults
    and bounds. Other fields are ignored, as they always were (the video is one of them)."""

    model_config = ConfigDict(extra="ignore")


class JobCreated(BaseModel):
    """A queued job; ``job_url`` follows its state and progress."""

    job_id: str = Field(examples=["0a1b2c3d4e5f60718293a4b5c6d7e8f9"])

    @computed_field(examples=["/jobs/0a1b2c3d4e5f60718293a4b5c6d7e8f9"])
    @property
    def job_url(self) -> str:
        return f"/jobs/{self.job_id}"


class AvatarCreated(JobCreated):
    """The job that learns the avatar; ``avatar_url`` has its metadata (``pending`` until done)."""

    avatar_id: str = Field(examples=["9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f"])

    @computed_field(examples=["/avatars/9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f"])
    @property
    def avatar_url(self) -> str:
        return f"/avatars/{self.avatar_id}"


def job_progress(job: JobRecord) -> dict[str, Any]:
    """The fields every view of a job shares: state, stage, progress, ETA, message and error."""
    return {
        "state": job.state,
        "stage": job.stage,
        "progress": round(job.progress, 4),
        "eta_seconds": job.eta_s,
        "message": job.message,
        "error": job.error,
    }


class JobInfo(BaseModel):
    """A job's state; ``progress`` runs 0..1 over all stages, ``eta_seconds`` while training (or
    rendering). ``kind``: ``avatar`` (makes ``avatar_id`` from a video: stages preprocess, align,
    train, export) or ``animation`` (makes ``animation_id``, an mp4 of the avatar ``avatar_id``
    performing a driving video: stages preprocess, align, render, export)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "job_id": "0a1b2c3d4e5f60718293a4b5c6d7e8f9",
                    "avatar_id": "9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f",
                    "state": "running",
                    "stage": "train",
                    "progress": 0.62,
                    "eta_seconds": 41.5,
                    "message": "iteration 150/600, 9120 Gaussians, loss 0.0412",
                    "error": None,
                    "attempts": 1,
                    "cancel_requested": False,
                    "filename": "me.mp4",
                    "options": JobOptions().model_dump(),
                    "created_at": "2026-11-22T17:00:00Z",
                    "started_at": "2026-11-22T17:00:01Z",
                    "finished_at": None,
                    "updated_at": "2026-11-22T17:01:10Z",
                }
            ]
        }
    )

    job_id: str
    kind: JobKindName = "avatar"
    avatar_id: str
    animation_id: str | None = None
    state: JobState
    stage: JobStage | None
    progress: float
    eta_seconds: float | None
    message: str | None
    error: str | None
    attempts: int
    cancel_requested: bool
    filename: str | None
    options: JobOptions | AnimationOptions
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime

    @classmethod
    def of(cls, job: JobRecord) -> JobInfo:
        kind = job_kind(job.kind)
        options = kind.options.model_validate(job.options)
        return cls(
            job_id=job.id,
            kind=kind.name,
            **kind.ids(job, options),
            **job_progress(job),
            attempts=job.attempts,
            cancel_requested=job.cancel_requested,
            filename=job.filename,
            options=options,
            created_at=utc_time(job.created_at),
            started_at=utc_time(job.started_at),
            finished_at=utc_time(job.finished_at),
            updated_at=utc_time(job.updated_at),
        )


class AvatarInfo(BaseModel):
    """An avatar: ``pending`` while its job runs, ``ready`` to render, or its job's end."""

    avatar_id: str
    job_id: str
    status: AvatarStatus
    created_at: datetime
    source_video: str | None = None
    error: str | None = None
    body_model: str | None = None
    preset: str | None = None
    num_gaussians: int | None = None
    iterations: int | None = None
    train_seconds: float | None = None
    final_loss: float | None = None
    metrics: dict[str, Any] = Field(
        default_factory=dict,
        description="Fit on training frames: psnr, ssim, lpips_alex (lpips_vgg, the "
        "perceptual score users compare, is the held-out quality report's).",
    )
    quality: QualityReport | None = Field(
        None,
        description="Scores on frames kept out of training (held_out) and what preprocessing saw of the "
        "person (detection); none for avatars made before it existed.",
    )
    num_frames: int | None = Field(
        None, description="Frames the avatar keeps (held-out ones too); render one with {'frame': i}."
    )
    frame_size: tuple[int, int] | None = Field(None, description="(height, width) of the training frames.")


class AvatarList(BaseModel):
    avatars: list[AvatarInfo]


class RenderRequest(RenderSpec):
    """Every key is optional: the default is the rest pose seen from the front, 512x512 PNG on white.

    ``frame`` renders training frame ``i`` with its fitted pose (and, unless ``camera`` is given,
    its camera and image size) to compare with the input video. The same schema as
    ``eva render`` (``eva_engine.avatar.RenderSpec``), plus the image ``format``.
    """

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [
                {
                    "pose": {
                        "joints": {"upperarm01.L": [0.0, 0.0, -1.1], "lowerarm01.L": [0.0, -1.2, 0.0]},
                        "expression": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8},
                    },
                    "camera": {"yaw": 30, "pitch": 5, "distance": 2.6},
                    "width": 512,
                    "height": 512,
                    "format": "png",
                },
                {"camera": "left", "background": [0, 0, 0], "format": "jpeg"},
                {"frame": 3},
            ]
        },
    )

    format: Literal["png", "jpeg"] = "png"
