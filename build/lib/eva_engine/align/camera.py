"""The camera guessed for a video without calibration."""

from __future__ import annotations

from torch import Tensor

from eva_engine.render import intrinsics, look_at

# A phone or webcam clip has no calibration: assume a 55 degree vertical field of view, a
# centred principal point and square pixels (typical of phone main cameras in video mode).
GUESS_FOV_Y_DEG = 55.0


def guess_camera(width: int, height: int, fov_y_deg: float = GUESS_FOV_Y_DEG) -> tuple[Tensor, Tensor]:
    """K [3, 3] and viewmat [4, 4] of the guessed camera: at the world origin, looking along -Z
    with Y up, so a subject facing +Z in front of it stands at negative z."""
    return intrinsics(width, height, fov_y_deg), look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
