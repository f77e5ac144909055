"""The face close-ups as a second view of each training frame.

A 512 px frame of a 1080p talking-head video leaves the eyes a few pixels tall: there a blink is
a change of about 3 px for the image terms. A dataset made from a larger video stores close-ups of
the face at the video's resolution (``data.face_crops``). Each step whose frame has one also
renders the close-up's camera from the same posed Gaussians and adds the frame's own objective
(``AvatarLoss``) on it, times ``weight``. Its screen-space gradients also count toward density
control, as a second view of the step (``densify``): the face gets the Gaussians its detail at the
video's resolution asks for, not only those the frame's few pixels do.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.render import Camera
from eva_engine.train.losses import composite_target


@dataclass(frozen=True)
class FaceViewConfig:
    """weight: the close-up's objective relative to the frame's (0: off); every: on every k-th
    step only, weighted k x weight there (the same expected gradient for less time); densify:
    the close-up's gradients (as weighted) join the frame's in density control (False: the
    frame's render alone decides, as before)."""

    weight: float = 0.0
    every: int = 1
    densify: bool = True

    def __post_init__(self) -> None:
        if self.weight < 0.0:
            raise ValueError(f"weight must be >= 0, got {self.weight}")
        if self.every < 1:
            raise ValueError(f"every must be >= 1, got {self.every}")


def _camera(frame) -> tuple[Tensor, Tensor]:
    return frame.K, frame.viewmat


class FaceViews:
    """The training frames' close-ups in memory: images [T, S, S, 3] uint8, masks [T, S, S] uint8
    and cameras, by training-frame position (None where a frame has none)."""

    def __init__(
        self, images: dict[int, Tensor], masks: dict[int, Tensor], cameras: dict[int, Camera]
    ) -> None:
        self.images, self.masks, self.cameras = images, masks, cameras

    @classmethod
    def load(cls, dataset, frame_ids: list[int], device: torch.device) -> FaceViews | None:
        """The close-ups of ``dataset``'s frames ``frame_ids`` (keyed by position in that list);
        None when the dataset has none."""
        crops = getattr(dataset, "face_crops", None)
        if crops is None:
            return None
        images, masks, cameras = {}, {}, {}
        for pos, i in enumerate(frame_ids):
            if not crops.has(i):
                continue
            images[pos] = (crops.image(i) * 255.0).round().to(torch.uint8).to(device)
            masks[pos] = (crops.mask(i) * 255.0).round().to(torch.uint8).to(device)
            # A loaded dataset holds its cameras; one in memory (DatasetLike) has them per frame.
            K, view = (dataset.K[i], dataset.viewmat[i]) if hasattr(dataset, "K") else _camera(dataset[i])
            cameras[pos] = Camera(crops.intrinsics(i, K), view.float(), crops.size, crops.size)
        return cls(images, masks, cameras) if images else None

    def __len__(self) -> int:
        return len(self.images)

    def view(self, pos: int, background: Tensor) -> tuple[Camera, Tensor, Tensor] | None:
        """(camera, target [S, S, 3] over ``background`` [3], mask [S, S]) of training frame
        ``pos``, or None."""
        if pos not in self.images:
            return None
        mask = self.masks[pos].float() / 255.0
        target = composite_target(self.images[pos].float() / 255.0, mask, background)
        return self.cameras[pos], target, mask
