"""In-the-wild preprocessing and body-model alignment (EVA §3.2, the plug-and-play module).

    from eva_engine.align import preprocess_video
    report = preprocess_video("clip.mp4", "data/datasets/clip")   # decode, detect, fit, write

Pieces: ``detect`` (MediaPipe Holistic -> the body models' keypoint layout), ``fit`` (staged
L-BFGS on the robust objective: ``targets``, ``stages``, ``objective``, ``initial``), ``clip``
(the fit over a clip's time axis), ``reprojection`` and ``evaluate`` (MPJPE and exact targets for
known clips), ``input_checks`` (the videos refused), ``preprocess`` (video -> dataset).
"""

from eva_engine.align.detect import DetectorConfig, DetectorError, FrameDetection, HolisticDetector
from eva_engine.align.evaluate import mpjpe, targets_from_params
from eva_engine.align.fit import FitResult, fit_sequence
from eva_engine.align.initial import initial_estimate
from eva_engine.align.input_checks import InputChecks
from eva_engine.align.preprocess import (
    Detections,
    PreprocessConfig,
    PreprocessError,
    PreprocessReport,
    detect_frames,
    preprocess_video,
)
from eva_engine.align.reprojection import reprojection_error
from eva_engine.align.scaling import scaled_fit_config
from eva_engine.align.stages import FitConfig, FitStage, default_stages
from eva_engine.align.targets import FitTargets

__all__ = [
    "Detections",
    "DetectorConfig",
    "DetectorError",
    "FitConfig",
    "FitResult",
    "FitStage",
    "FitTargets",
    "FrameDetection",
    "HolisticDetector",
    "InputChecks",
    "PreprocessConfig",
    "PreprocessError",
    "PreprocessReport",
    "default_stages",
    "detect_frames",
    "fit_sequence",
    "initial_estimate",
    "mpjpe",
    "preprocess_video",
    "reprojection_error",
    "scaled_fit_config",
    "targets_from_params",
]
