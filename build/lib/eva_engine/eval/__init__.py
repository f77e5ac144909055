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
from eva_engine.eval.quality import QualityReport, VerdictRules, held_out_every, quality_report, verdict

__all__ = [
    "METRICS",
    "REGIONS",
    "EvalResult",
    "ImageMetrics",
    "PoseRefinement",
    "QualityReport",
    "VerdictRules",
    "RegionMetrics",
    "evaluate_avatar",
    "held_out_every",
    "metrics_table",
    "quality_report",
    "verdict",
]
