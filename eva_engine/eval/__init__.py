"""Evaluating avatars on novel-pose frames: full / hand / face metrics in the paper's Table 1
layout (``evaluate_avatar``, ``metrics_table``), with LPIPS-VGG as the held-out headline."""

from eva_engine.eval.evaluate import (
    METRICS,
    REGIONS,
    EvalResult,
    ImageMetrics,
    PoseRefinement,
    RegionMetrics,
    evaluate_avatar,
    metrics_table,
)

__all__ = [
    "METRICS",
    "REGIONS",
    "EvalResult",
    "ImageMetrics",
    "PoseRefinement",
    "RegionMetrics",
    "evaluate_avatar",
    "metrics_table",
]
