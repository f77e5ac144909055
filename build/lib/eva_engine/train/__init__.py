"""Training a Gaussian avatar (EVA §3.3-3.4 and §4.1): configs and presets, losses, density
control strategies, and the loop.

    from eva_engine.data import load_dataset
    from eva_engine.train import preset, train_avatar
    result = train_avatar(load_dataset(path), preset("default"), progress=print)
"""

from eva_engine.recipes import METHODS, PRESETS
from eva_engine.train.confidence import ConfidenceConfig, ConfidenceLoss, ConfidenceNet
from eva_engine.train.config import OptimConfig, TrainConfig, preset, with_overrides
from eva_engine.train.losses import (
    PHOTOMETRIC_LOSSES,
    AvatarLoss,
    L1Loss,
    LossConfig,
    PhotometricLoss,
    composite_target,
)
from eva_engine.train.methods import with_method
from eva_engine.train.pose_correction import PoseCorrection, PoseCorrectionConfig
from eva_engine.train.strategy import ContextAwareStrategy, DefaultStrategy, KLStrategy, Strategy
from eva_engine.train.trainer import (
    STAGES,
    TrainingError,
    TrainResult,
    dataset_background,
    load_training_frames,
    train_avatar,
)

__all__ = [
    "METHODS",
    "PHOTOMETRIC_LOSSES",
    "PRESETS",
    "STAGES",
    "AvatarLoss",
    "ConfidenceConfig",
    "ConfidenceLoss",
    "ConfidenceNet",
    "ContextAwareStrategy",
    "DefaultStrategy",
    "KLStrategy",
    "L1Loss",
    "LossConfig",
    "OptimConfig",
    "PhotometricLoss",
    "PoseCorrection",
    "PoseCorrectionConfig",
    "Strategy",
    "TrainConfig",
    "TrainResult",
    "TrainingError",
    "composite_target",
    "dataset_background",
    "load_training_frames",
    "preset",
    "train_avatar",
    "with_method",
    "with_overrides",
]
