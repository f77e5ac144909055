"""Pinhole cameras in the project's conventions.

World: Y up, the subject faces +Z, metres. Cameras: OpenCV axes (x right, y down, z forward),
``viewmat`` [4, 4] world->camera, ``K`` [3, 3] in pixels with pixel (x, y) centred at
(x + 0.5, y + 0.5), so a centred principal point is (W / 2, H / 2).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.geometry import camera_center


@dataclass
class Camera:
    """K: [3, 3] intrinsics in pixels; viewmat: [4, 4] world -> camera (x right, y down, z forward);
    width, height: image size in pixels."""

    K: Tensor
    viewmat: Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3) or tuple(self.viewmat.shape) != (4, 4):
            raise ValueError(
                f"K must be [3, 3] and viewmat [4, 4], got {tuple(self.K.shape)}, {tuple(self.viewmat.shape)}"
            )
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Camera:
        return Camera(self.K.to(device, dtype), self.viewmat.to(device, dtype), self.width, self.height)

    def scaled(self, factor: int) -> Camera:
        """The same view at ``factor`` times the pixels across (a sharper render of one frame)."""
        if factor < 1:
            raise ValueError(f"factor must be a positive integer, got {factor}")
        K = self.K.clone()
        K[:2] *= factor
        return Camera(K, self.viewmat, self.width * factor, self.height * factor)

    @property
    def center(self) -> Tensor:
        """[3] camera centre in world coordinates."""
        return camera_center(self.viewmat)


def intrinsics(width: int, height: int, fov_y_deg: float) -> Tensor:
    """[3, 3] float32 K of a centred pinhole with square pixels and vertical field of view ``fov_y_deg``."""
    if not (0.0 < fov_y_deg < 180.0):
        raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float32)


def look_at(
    eye: Sequence[float] | Tensor,
    target: Sequence[float] | Tensor,
    up: Sequence[float] | Tensor = (0.0, 1.0, 0.0),
) -> Tensor:
    """[4, 4] float32 world->camera matrix of a camera at ``eye`` looking at ``target``.

    The image's "up" (-y) is the projection of ``up``; ``eye == target`` or ``up`` parallel to
    the viewing direction has no answer and raises ValueError.
    """
    eye_t, target_t, up_t = (torch.as_tensor(v, dtype=torch.float64).reshape(3) for v in (eye, target, up))
    forward = target_t - eye_t
    if forward.norm() < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up_t)
    if right.norm() < 1e-9 * max(up_t.norm().item(), 1e-30):
        raise ValueError("look_at: up is parallel to the viewing direction")
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye_t
    return view.float()


def orbit_camera(
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    distance: float = 3.0,
    target: Sequence[float] | Tensor = (0.0, 0.0, 0.0),
) -> Tensor:
    """[4, 4] world->camera of a camera on a sphere around ``target``, looking at it.

    yaw 0, pitch 0 is in front of the subject (on +Z); positive yaw moves the camera toward the
    subject's left (+X), positive pitch raises it (+Y). ``distance`` > 0 in metres.
    """
    if not distance > 0 or not math.isfinite(distance):
        raise ValueError(f"distance must be a positive finite number of metres, got {distance}")
    if abs(pitch_deg) >= 90.0:
        raise ValueError(f"pitch must be strictly between -90 and 90 degrees, got {pitch_deg}")
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    offset = (
        distance * math.cos(pitch) * math.sin(yaw),
        distance * math.sin(pitch),
        distance * math.cos(pitch) * math.cos(yaw),
    )
    target_t = torch.as_tensor(target, dtype=torch.float64).reshape(3)
    return look_at(target_t + torch.tensor(offset, dtype=torch.float64), target_t)
