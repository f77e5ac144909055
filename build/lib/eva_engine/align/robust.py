"""Robust error functions of the fitting objective (EVA eq. 10-12).

Geman-McClure: ``psi(r) = sigma^2 r^2 / (sigma^2 + r^2)`` per coordinate residual r (the
SMPLify form): quadratic (r^2) for |r| << sigma, bounded by sigma^2 for outliers, so one wrong
detection cannot drag the fit. Its gradient ``2 r sigma^4 / (sigma^2 + r^2)^2`` vanishes for
large residuals.
"""

from __future__ import annotations

from torch import Tensor


def geman_mcclure(residual: Tensor, sigma: float) -> Tensor:
    """Elementwise psi(r) for ``residual`` of any shape; sigma > 0 in the residual's units."""
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    s2 = sigma * sigma
    r2 = residual * residual
    return s2 * r2 / (s2 + r2)


def weighted_gm(residual: Tensor, weights: Tensor, sigma: float) -> Tensor:
    """Sum over points of ``weights * sum_coords psi(residual)`` divided by the weight total.

    residual: [..., K, C]; weights: [..., K] (per-point weight times confidence; 0 = ignore).
    The normalisation keeps the term's scale independent of how many points were detected;
    with no weight at all it is 0 with a zero (finite) gradient.
    """
    per_point = geman_mcclure(residual, sigma).sum(-1)
    return (weights * per_point).sum() / weights.sum().clamp_min(1e-8)


def z_only_gm(model_points: Tensor, target_points: Tensor, weights: Tensor, sigma: float) -> Tensor:
    """The hand prior psi_z (EVA eq. 12): only relative depth counts.

    model_points, target_points: [..., K, 3] in camera coordinates (z along the optical axis),
    each expressed relative to its own root point (index 0, the wrist), so only the depth
    *pattern* of the fingers is compared, not the hand's absolute depth; weights: [..., K].
    """
    model_z = model_points[..., 2] - model_points[..., :1, 2]
    target_z = target_points[..., 2] - target_points[..., :1, 2]
    return weighted_gm((model_z - target_z)[..., None], weights, sigma)
