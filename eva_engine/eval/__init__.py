"""Evaluating avatars on novel-pose frames: full / hand / face metrics in the paper's Table 1
layout (``evaluate_avatar``, ``metrics_table``)."""

from eva_engine.eval.evaluate import (
    REGIONS,
    EvalResult,
    RegionMetrics,
    evaluate_avatar,
    image_metrics,
    metrics_table,
)

__all__ = ["REGIONS", "EvalResult", "RegionMetrics", "evaluate_avatar", "image_metrics", "metrics_table"]
