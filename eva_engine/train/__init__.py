"""Training a Gaussian avatar (EVA §3.3-3.4 and §4.1): configs and presets, losses, density
control strategies, and the loop.

    from eva_engine.data import load_dataset
    from eva_engine.train import preset, train_avatar
    result = train_avatar(load_dataset(path), preset("default"), progress=print)
"""

from eva_engine.train.config import PRESETS, OptimConfig, TrainConfig, preset
from eva_engine.train.losses import (
    PHOTOMETRIC_LOSSES,
    AvatarLoss,
    L1Loss,
    LossConfig,
    PhotometricLoss,
    composite_target,
)
from eva_engine.train.strategy import DefaultStrategy, Strategy
from eva_engine.train.trainer import (
    STAGES,
    TrainingError,
    TrainProgress,
    TrainResult,
    dataset_background,
    load_training_frames,
    train_avatar,
)

__all__ = [
    "PHOTOMETRIC_LOSSES",
    "PRESETS",
    "STAGES",
    "AvatarLoss",
    "DefaultStrategy",
    "L1Loss",
    "LossConfig",
    "OptimConfig",
    "PhotometricLoss",
    "Strategy",
    "TrainConfig",
    "TrainProgress",
    "TrainResult",
    "TrainingError",
    "composite_target",
    "dataset_background",
    "load_training_frames",
    "preset",
    "train_avatar",
]
