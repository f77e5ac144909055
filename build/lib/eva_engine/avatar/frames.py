"""The training frames kept with an avatar: each frame's fitted body parameters and camera, so the
avatar can be rendered in a training frame's pose and view to compare with the input video (the
render endpoint's ``frame``, ``eva render --pose frame:N``). ``eva_engine.avatar.io`` stores them
in the avatar directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from eva_engine.body.params import BodyParams

if TYPE_CHECKING:
    from eva_engine.data.dataset import Dataset


@dataclass
class AvatarFrames:
    """params: the frames' body parameters (batch F); K [F, 3, 3]; viewmat [F, 4, 4];
    timestamps [F] float64 seconds; image_size: (height, width) in pixels, (0, 0) when unknown;
    fps: the frame rate of the source (0 when unknown)."""

    params: BodyParams
    K: torch.Tensor
    viewmat: torch.Tensor
    timestamps: torch.Tensor
    image_size: tuple[int, int] = (0, 0)
    fps: float = 0.0

    def __len__(self) -> int:
        return self.params.batch_size

    @classmethod
    def of_dataset(cls, dataset: Dataset, params: BodyParams | None = None) -> AvatarFrames:
        """All of ``dataset``'s frames, with ``params`` (batch F; e.g. ``TrainResult.frame_params``:
        the fits as trained, pose-corrected) in place of the dataset's own fits when given."""
        params = params if params is not None else dataset.params
        if params is None:
            raise ValueError("the dataset has no body parameters to keep with the avatar")
        if params.batch_size != len(dataset.timestamps):
            raise ValueError(f"{params.batch_size} frame params for {len(dataset.timestamps)} frames")
        h, w = dataset.meta.image_size
        return cls(
            params=params.map(lambda t: t.detach().cpu().float()),
            K=dataset.K.float(),
            viewmat=dataset.viewmat.float(),
            timestamps=torch.as_tensor(dataset.timestamps, dtype=torch.float64),
            image_size=(int(h), int(w)),
            fps=float(dataset.meta.fps),
        )
