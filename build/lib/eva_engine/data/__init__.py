"""Data in and out of the engine: video frames, the dataset layout and its loader, region masks,
parameter noise for ablations, and readers for public datasets. The on-disk layout is documented
in ``docs/dataset-format.md``. The synthetic benchmark is ``eva_engine.synth``."""

from __future__ import annotations

from eva_engine.data.dataset import (
    REGION_MASKS,
    Dataset,
    DatasetError,
    DatasetLike,
    DatasetMeta,
    DatasetWriter,
    Frame,
    ParamNames,
    load_dataset,
)
from eva_engine.data.perturb import PerturbConfig, perturb
from eva_engine.data.resampled import ResampledDataset, resample_frame
from eva_engine.data.video import (
    VideoClip,
    VideoError,
    VideoReadOptions,
    iter_frames,
    iter_timed_frames,
    read_video,
    write_video,
)

__all__ = [
    "REGION_MASKS",
    "Dataset",
    "DatasetError",
    "DatasetLike",
    "DatasetMeta",
    "DatasetWriter",
    "Frame",
    "ParamNames",
    "PerturbConfig",
    "ResampledDataset",
    "VideoClip",
    "VideoError",
    "VideoReadOptions",
    "load_dataset",
    "perturb",
    "iter_frames",
    "iter_timed_frames",
    "read_video",
    "resample_frame",
    "write_video",
]
