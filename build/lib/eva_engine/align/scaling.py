"""``scaled_fit_config``: the alignment's iteration budget scaled by one factor (``--fit-scale``,
the ``fit_scale`` option of the service), for quicker fits of driving videos and tests."""

from __future__ import annotations

import dataclasses

from eva_engine.align.stages import FitConfig


def scaled_fit_config(scale: float, base: FitConfig | None = None) -> FitConfig:
    """``base`` (default ``FitConfig()``) with every stage's L-BFGS iterations and the IK
    iterations multiplied by ``scale`` > 0 (at least 1 each); 1 returns ``base`` unchanged."""
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    base = base or FitConfig()
    if scale == 1.0:
        return base
    stages = tuple(
        dataclasses.replace(st, iterations=max(1, round(st.iterations * scale))) for st in base.stages
    )
    return dataclasses.replace(base, stages=stages, ik_iterations=max(1, round(base.ik_iterations * scale)))
