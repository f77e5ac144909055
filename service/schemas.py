"""The API's contract: request and response models (with the examples shown at ``/docs``)."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    field_validator,
    model_validator,
)

from eva_engine.body import BodyPose
from jobs.options import JobOptions
from jobs.store import JobRecord

# Physical bounds of what a client may ask for: finite is not enough (1e300 becomes inf in
# float32 and renders a blank image), and a bounded request has a bounded cost.
MAX_POSE_KEYS = 256
MAX_ROTATION = 2.0 * math.pi  # radians: every rotation has an axis-angle of norm <= pi
MAX_TRANSLATION_M = 10.0
MAX_CAMERA_DISTANCE_M = 100.0
MAX_PIXELS_COORD = 1e5  # K's entries
EXPRESSION_RANGE = 3.0  # SMPL-X's coefficients are standard deviations; Anny's [0, 1] is the model's own
SHAPE_RANGE = 5.0
MAX_SIDE = 4096
MAX_FRAME_INDEX = 100_000


def _rotation(value: tuple[float, float, float]) -> tuple[float, float, float]:
    if math.hypot(*value) > MAX_ROTATION:
        raise ValueError(
            f"an axis-angle rotation must have a norm of at most 2 pi ({MAX_ROTATION:.4f}) radians"
        )
    return value


Name = Annotated[str, StringConstraints(min_length=1, max_length=64)]
Angle = Annotated[float, Field(ge=-MAX_ROTATION, le=MAX_ROTATION)]
AxisAngle = Annotated[tuple[Angle, Angle, Angle], AfterValidator(_rotation)]
Metres = Annotated[float, Field(ge=-MAX_TRANSLATION_M, le=MAX_TRANSLATION_M)]
Position = tuple[Metres, Metres, Metres]
Pixels = Annotated[float, Field(ge=-MAX_PIXELS_COORD, le=MAX_PIXELS_COORD)]
Vec3 = tuple[Pixels, Pixels, Pixels]
ViewEntry = Annotated[float, Field(ge=-MAX_CAMERA_DISTANCE_M, le=MAX_CAMERA_DISTANCE_M)]
Vec4 = tuple[ViewEntry, ViewEntry, ViewEntry, ViewEntry]
Unit = Annotated[float, Field(ge=0.0, le=1.0)]

JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JobStage = Literal["preprocess", "align", "train", "export"]
AvatarStatus = Literal["pending", "ready", "failed", "cancelled"]

# Named views of the subject (yaw toward the subject's left is positive; see render.camera).
CAMERA_PRESETS: dict[str, dict[str, float]] = {
    "front": {"yaw": 0.0, "pitch": 0.0},
    "back": {"yaw": 180.0, "pitch": 0.0},
    "left": {"yaw": 90.0, "pitch": 0.0},
    "right": {"yaw": -90.0, "pitch": 0.0},
    "front_left": {"yaw": 45.0, "pitch": 10.0},
    "front_right": {"yaw": -45.0, "pitch": 10.0},
    "above": {"yaw": 0.0, "pitch": 45.0},
}
DEFAULT_DISTANCE, DEFAULT_FOV_Y, DEFAULT_SIZE = 2.6, 40.0, 512


def _time(ts: float | None) -> datetime | None:
    return datetime.fromtimestamp(ts, UTC) if ts is not None else None


class ErrorMessage(BaseModel):
    detail: str = Field(examples=["no avatar with id 0123456789abcdef0123456789abcdef"])


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    version: str
    queue: str = Field(description="sqlite or redis")
    jobs: dict[str, int] = Field(description="Job count per state.")
    renders: dict[str, int] = Field(default_factory=dict, description="Renders running and waiting.")


class AvatarCreated(BaseModel):
    avatar_id: str = Field(examples=["9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f"])
    job_id: str = Field(examples=["0a1b2c3d4e5f60718293a4b5c6d7e8f9"])
    job_url: str = Field(examples=["/jobs/0a1b2c3d4e5f60718293a4b5c6d7e8f9"])
    avatar_url: str = Field(examples=["/avatars/9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f"])


class JobInfo(BaseModel):
    """A job's state; ``progress`` runs 0..1 over all stages, ``eta_seconds`` while training."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "job_id": "0a1b2c3d4e5f60718293a4b5c6d7e8f9", "avatar_id": "9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f",
        "state": "running", "stage": "train", "progress": 0.62, "eta_seconds": 41.5,
        "message": "iteration 150/600, 9120 Gaussians, loss 0.0412", "error": None, "attempts": 1,
        "cancel_requested": False, "filename": "me.mp4", "options": JobOptions().model_dump(),
        "created_at": "2026-11-22T17:00:00Z", "started_at": "2026-11-22T17:00:01Z",
        "finished_at": None, "updated_at": "2026-11-22T17:01:10Z",
    }]})  # fmt: skip

    job_id: str
    avatar_id: str
    state: JobState
    stage: JobStage | None
    progress: float
    eta_seconds: float | None
    message: str | None
    error: str | None
    attempts: int
    cancel_requested: bool
    filename: str | None
    options: JobOptions
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime

    @classmethod
    def of(cls, job: JobRecord) -> JobInfo:
        return cls(
            job_id=job.id, avatar_id=job.avatar_id, state=job.state, stage=job.stage,  # type: ignore[arg-type]
            progress=round(job.progress, 4), eta_seconds=job.eta_s, message=job.message, error=job.error,
            attempts=job.attempts, cancel_requested=job.cancel_requested, filename=job.filename,
            options=JobOptions.model_validate(job.options), created_at=_time(job.created_at),
            started_at=_time(job.started_at), finished_at=_time(job.finished_at),
            updated_at=_time(job.updated_at),
        )  # fmt: skip


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
        default_factory=dict, description="Fit on training frames: psnr, ssim, lpips_vgg, lpips_alex."
    )
    num_frames: int | None = Field(None, description="Training frames; render one with {'frame': i}.")
    frame_size: tuple[int, int] | None = Field(None, description="(height, width) of the training frames.")


class AvatarList(BaseModel):
    avatars: list[AvatarInfo]


class RenderPose(BodyPose):
    """``BodyPose`` with the bounds a render request must keep: at most 256 names per dict (of at
    most 64 characters), axis-angles of norm <= 2 pi, translation within 10 m, expression within
    +-3 and shape within +-5 (and within the body model's own range, checked when rendering)."""

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


class CameraSpec(BaseModel):
    """Either an orbit around ``target`` (yaw, pitch in degrees; distance in metres; vertical field
    of view ``fov_y`` in degrees) or explicit OpenCV ``K`` [3x3] (pixels, for the requested size)
    and world->camera ``viewmat`` [4x4]. A JSON string names a preset view instead."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    yaw: float | None = Field(None, ge=-360.0, le=360.0)
    pitch: float | None = Field(None, gt=-90.0, lt=90.0)
    distance: float | None = Field(None, gt=0.0, le=MAX_CAMERA_DISTANCE_M)
    target: Position | None = None
    fov_y: float | None = Field(None, gt=1.0, lt=170.0)
    K: tuple[Vec3, Vec3, Vec3] | None = None
    viewmat: tuple[Vec4, Vec4, Vec4, Vec4] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> CameraSpec:
        orbit = [k for k in ("yaw", "pitch", "distance", "target", "fov_y") if getattr(self, k) is not None]
        if self.K is None and self.viewmat is None:
            return self
        if self.K is None or self.viewmat is None:
            raise ValueError("give both 'K' and 'viewmat' (or neither, for an orbit camera)")
        if orbit:
            raise ValueError(f"{orbit} cannot be combined with 'K' and 'viewmat'")
        k = self.K
        if not (k[0][0] >= 1.0 and k[1][1] >= 1.0 and k[1][0] == 0 and k[2] == (0.0, 0.0, 1.0)):
            raise ValueError("K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy >= 1 pixel")
        v = self.viewmat
        if v[3] != (0.0, 0.0, 0.0, 1.0):
            raise ValueError("viewmat's last row must be [0, 0, 0, 1]")
        r = [row[:3] for row in v[:3]]
        for i in range(3):
            for j in range(3):
                dot = sum(r[i][n] * r[j][n] for n in range(3))
                if not math.isclose(dot, 1.0 if i == j else 0.0, abs_tol=1e-3):
                    raise ValueError("viewmat's upper-left 3x3 must be a rotation (orthonormal rows)")
        return self


class RenderRequest(BaseModel):
    """Every key is optional: the default is the rest pose seen from the front, 512x512 PNG on white.

    ``frame`` renders training frame ``i`` with its fitted pose (and, unless ``camera`` is given,
    its camera and image size) to compare with the input video.
    """

    model_config = ConfigDict(
        extra="forbid", allow_inf_nan=False,
        json_schema_extra={"examples": [
            {"pose": {"joints": {"upperarm01.L": [0.0, 0.0, -1.1], "lowerarm01.L": [0.0, -1.2, 0.0]},
                      "expression": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8}},
             "camera": {"yaw": 30, "pitch": 5, "distance": 2.6}, "width": 512, "height": 512,
             "format": "png"},
            {"camera": "left", "background": [0, 0, 0], "format": "jpeg"},
            {"frame": 3},
        ]},
    )  # fmt: skip

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
    format: Literal["png", "jpeg"] = "png"

    @field_validator("camera", mode="before")
    @classmethod
    def _preset(cls, value):
        if isinstance(value, str):
            if value not in CAMERA_PRESETS:
                raise ValueError(f"unknown camera preset {value!r}; choose one of {list(CAMERA_PRESETS)}")
            return CAMERA_PRESETS[value]
        return value

    @model_validator(mode="after")
    def _pose_or_frame(self) -> RenderRequest:
        if self.pose is not None and self.frame is not None:
            raise ValueError("give 'pose' or 'frame', not both")
        return self
