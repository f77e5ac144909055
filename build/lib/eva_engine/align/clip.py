"""Aligning the body model to a whole clip: the steps around the L-BFGS fit that use the clip's
time axis (``fit.fit_sequence`` sees frames, not time).

    result = fit_clip(model, targets, times, FitConfig())

1. Hand detections on the wrong side are dropped (``hands.reject_wrong_hands``).
2. The initial estimate (``initial.initial_estimate``), then the staged fit (``fit.fit_sequence``).
3. Frames where a hand was not found get that hand's pose interpolated from the neighbouring
   detections (``hands.fill_hand_gaps``), with a per-frame confidence.
4. The expression may be smoothed over time (a Gaussian of ``FitConfig.expression_sigma``
   seconds; off by default, since a blink lasts only a few frames).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.align.fit import fit_sequence
from eva_engine.align.hands import fill_hand_gaps, hand_found, reject_wrong_hands
from eva_engine.align.initial import initial_estimate
from eva_engine.align.stages import FitConfig
from eva_engine.align.targets import FitTargets
from eva_engine.body import BodyModel, BodyParams


@dataclass
class ClipFit:
    """params: the fitted clip with the hands' gaps filled; initial: the initial estimate;
    targets: what was fitted (wrong-side hands removed); hand_confidence: [F, 2] (left, right) 1
    where the hand was detected, in (0, 1) where interpolated, 0 where unknown; hands_rejected:
    [F, 2] bool; seconds: wall time."""

    params: BodyParams
    initial: BodyParams
    targets: FitTargets
    hand_confidence: Tensor
    hands_rejected: Tensor
    seconds: float


def fit_clip(
    model: BodyModel, targets: FitTargets, times: Tensor, config: FitConfig | None = None
) -> ClipFit:
    """Align ``model`` to a clip's detections (module docstring). times: [F] seconds."""
    config = config or FitConfig()
    started = time.perf_counter()
    keypoints, rejected = reject_wrong_hands(targets.keypoints, config.hands)
    targets = dataclasses.replace(targets, keypoints=keypoints)
    init = initial_estimate(model, targets, config)
    fitted = fit_sequence(model, targets, init=init, config=config).params
    params, confidence = fill_hand_gaps(
        model, fitted, hand_found(keypoints), torch.as_tensor(times), config.hands
    )
    params.expression = smooth_over_time(params.expression, torch.as_tensor(times), config.expression_sigma)
    return ClipFit(params, init, targets, confidence, rejected, time.perf_counter() - started)


def smooth_over_time(values: Tensor, times: Tensor, sigma: float) -> Tensor:
    """values [F, D] filtered along the frames by a Gaussian of ``sigma`` seconds (weights
    renormalised at the clip's ends and across uneven frame times); sigma 0: unchanged."""
    if sigma <= 0 or values.shape[0] < 2:
        return values
    t = times.to(torch.float64)
    w = torch.exp(-0.5 * ((t[:, None] - t[None, :]) / sigma) ** 2)
    w = w / w.sum(dim=1, keepdim=True)
    return (w.to(values.dtype) @ values).contiguous()
