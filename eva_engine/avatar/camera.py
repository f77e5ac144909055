"""``Camera``: one pinhole view in the project's OpenCV convention."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


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
            raise ValueError(f"K must be [3, 3] and viewmat [4, 4], got {tuple(self.K.shape)}, "
                             f"{tuple(self.viewmat.shape)}")  # fmt: skip
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> Camera:
        return Camera(self.K.to(device, dtype), self.viewmat.to(device, dtype), self.width, self.height)

    @property
    def center(self) -> Tensor:
        """[3] camera centre in world coordinates."""
        r, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -(r.T @ t)
