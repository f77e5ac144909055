"""Camera projection for fitting, and the camera guessed for a video without calibration."""

from __future__ import annotations

from torch import Tensor

from eva_engine.render import intrinsics, look_at

# A phone or webcam clip has no calibration: assume a 55 degree vertical field of view, a
# centred principal point and square pixels (typical of phone main cameras in video mode).
GUESS_FOV_Y_DEG = 55.0
MIN_DEPTH = 0.05


def guess_camera(width: int, height: int, fov_y_deg: float = GUESS_FOV_Y_DEG) -> tuple[Tensor, Tensor]:
    """K [3, 3] and viewmat [4, 4] of the guessed camera: at the world origin, looking along -Z
    with Y up, so a subject facing +Z in front of it stands at negative z."""
    return intrinsics(width, height, fov_y_deg), look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))


def to_camera(points: Tensor, viewmat: Tensor) -> Tensor:
    """points [B, N, 3] world, viewmat [B, 4, 4] or [4, 4] -> [B, N, 3] camera coordinates."""
    rot, t = viewmat[..., :3, :3], viewmat[..., :3, 3]
    if viewmat.ndim == 2:
        return points @ rot.T + t
    return points @ rot.transpose(-1, -2) + t[:, None]


def project(points_cam: Tensor, K: Tensor) -> Tensor:
    """[B, N, 3] camera coordinates -> [B, N, 2] pixels. Depth is clamped at 5 cm so points at or
    behind the camera stay finite (their residuals are large and bounded by the robust loss)."""
    z = points_cam[..., 2:3].clamp_min(MIN_DEPTH)
    uv = points_cam[..., :2] / z
    if K.ndim == 2:
        return uv * K.diagonal()[:2] + K[:2, 2]
    return uv * K.diagonal(dim1=-2, dim2=-1)[:, None, :2] + K[:, None, :2, 2]
