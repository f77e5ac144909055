"""``CameraSpec``: a camera as JSON, the one schema the API, the CLI and the web page share.

Either an orbit around a target (yaw, pitch in degrees, distance in metres, vertical field of
view), explicit OpenCV ``K`` and world->camera ``viewmat`` matrices, or a training frame's camera
(``frame``; yaw and pitch then turn it about the body: ``avatar.render_spec``); a string names one
of :data:`CAMERA_PRESETS` instead. ``eva_engine.render.view.camera_from_spec`` turns an orbit or
K/viewmat into a ``Camera`` for an image size; this module loads no torch.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

# Physical bounds of a camera: finite is not enough (1e300 becomes inf in float32 and renders a
# blank image), and a bounded request has a bounded cost.
MAX_TRANSLATION_M = 10.0  # a target (and a pose's root translation) within 10 m of the origin
MAX_CAMERA_DISTANCE_M = 100.0
MAX_PIXELS_COORD = 1e5  # K's entries
MAX_FRAME_INDEX = 100_000

Metres = Annotated[float, Field(ge=-MAX_TRANSLATION_M, le=MAX_TRANSLATION_M)]
Position = tuple[Metres, Metres, Metres]
Pixels = Annotated[float, Field(ge=-MAX_PIXELS_COORD, le=MAX_PIXELS_COORD)]
Vec3 = tuple[Pixels, Pixels, Pixels]
ViewEntry = Annotated[float, Field(ge=-MAX_CAMERA_DISTANCE_M, le=MAX_CAMERA_DISTANCE_M)]
Vec4 = tuple[ViewEntry, ViewEntry, ViewEntry, ViewEntry]

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


class CameraSpec(BaseModel):
    """Either an orbit around ``target`` (yaw, pitch in degrees; distance in metres; vertical field
    of view ``fov_y`` in degrees), explicit OpenCV ``K`` [3x3] (pixels, for the requested size)
    and world->camera ``viewmat`` [4x4], or ``frame``: training frame i's camera where it was
    relative to the body (so a new pose is framed as the video framed the person), turned by
    ``yaw`` and ``pitch`` about the body. A JSON string names a preset view instead."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    yaw: float | None = Field(None, ge=-360.0, le=360.0)
    pitch: float | None = Field(None, gt=-90.0, lt=90.0)
    distance: float | None = Field(None, gt=0.0, le=MAX_CAMERA_DISTANCE_M)
    target: Position | None = None
    fov_y: float | None = Field(None, gt=1.0, lt=170.0)
    K: tuple[Vec3, Vec3, Vec3] | None = None
    viewmat: tuple[Vec4, Vec4, Vec4, Vec4] | None = None
    frame: int | None = Field(
        None,
        ge=0,
        le=MAX_FRAME_INDEX,
        description="Training frame i's camera, placed relative to the body as it was in that frame; "
        "yaw and pitch (degrees) turn it about the body.",
    )

    @model_validator(mode="after")
    def _one_kind(self) -> CameraSpec:
        if self.frame is not None:
            other = [
                k for k in ("distance", "target", "fov_y", "K", "viewmat") if getattr(self, k) is not None
            ]
            if other:
                raise ValueError(f"{other} cannot be combined with 'frame' (only yaw and pitch turn it)")
            return self
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

    @property
    def is_orbit(self) -> bool:
        return self.K is None and self.frame is None


def camera_preset(value):
    """A preset name -> its orbit dict (for ``field_validator(mode="before")``); anything else
    passes through unchanged."""
    if isinstance(value, str):
        if value not in CAMERA_PRESETS:
            raise ValueError(f"unknown camera preset {value!r}; choose one of {list(CAMERA_PRESETS)}")
        return CAMERA_PRESETS[value]
    return value
