"""``ResampledDataset``: a dataset seen at another image resolution, frame by frame, without
rewriting it (``TrainConfig.image_scale``; benchmarks that train and test at a lower one)."""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F

from eva_engine.body.params import BodyParams
from eva_engine.data.dataset import DatasetLike, DatasetMeta, Frame


def resample_frame(frame: Frame, scale: float) -> Frame:
    """``frame`` with its image, masks and intrinsics resampled by ``scale``: each side becomes
    ``round(side * scale)`` pixels (at least 1), area-averaged, and K follows (pixel centres stay
    at (x + 0.5, y + 0.5)). ``scale`` 1 returns the frame as it is."""
    if scale == 1.0:
        return frame
    h, w = frame.image.shape[:2]
    size = (max(1, round(h * scale)), max(1, round(w * scale)))

    def area(mask: torch.Tensor) -> torch.Tensor:  # [H, W] -> [h, w]
        return F.interpolate(mask.float()[None, None], size=size, mode="area")[0, 0]

    image = F.interpolate(frame.image.float().permute(2, 0, 1)[None], size=size, mode="area")[0]
    K = frame.K.float().clone()
    K[0] *= size[1] / w
    K[1] *= size[0] / h
    return dataclasses.replace(
        frame,
        image=image.permute(1, 2, 0),
        mask=area(frame.mask),
        K=K,
        regions={name: area(m) for name, m in frame.regions.items()},
    )


class ResampledDataset:
    """``dataset`` (a :class:`DatasetLike`) with every frame resampled by ``scale``
    (:func:`resample_frame`); splits, body parameters and cameras' poses are the dataset's own."""

    def __init__(self, dataset: DatasetLike, scale: float) -> None:
        if not scale > 0.0:
            raise ValueError(f"scale must be > 0, got {scale}")
        self.dataset, self.scale = dataset, scale
        h, w = dataset.meta.image_size
        size = (max(1, round(h * scale)), max(1, round(w * scale)))
        self.meta: DatasetMeta = dataclasses.replace(dataset.meta, image_size=size)

    @property
    def splits(self) -> dict[str, list[int]]:
        return self.dataset.splits

    @property
    def params(self) -> BodyParams | None:
        return self.dataset.params

    @property
    def gt_params(self) -> BodyParams | None:
        return self.dataset.gt_params

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> Frame:
        return resample_frame(self.dataset[i], self.scale)
