"""Noise on body parameters that imitates off-the-shelf estimators, for the alignment study and the
"w/o Align" ablation: small body-joint error, larger hand and finger error, global jitter of the
root, a little expression error, and one shape error for the whole sequence (one subject).

Errors are a per-sequence bias plus per-frame jitter (estimators are biased and jittery), and
scale linearly with ``level`` (0 = no change, 1 = typical of a good estimator).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from eva_engine.body import PART_NAMES, BodyModel, BodyParams


@dataclasses.dataclass(frozen=True)
class PerturbConfig:
    """Standard deviations at ``level = 1`` (radians, metres, coefficient units)."""

    body_joint: float = 0.04
    hand_joint: float = 0.16
    root_orient: float = 0.03
    transl: float = 0.015
    expression: float = 0.08
    shape: float = 0.05
    bias_fraction: float = 0.5
    """Share of the variance that is a per-sequence bias rather than per-frame jitter."""


def _noise(shape: Sequence[int], sigma: float, bias_fraction: float, gen: torch.Generator) -> torch.Tensor:
    """[N, ...] noise: a bias shared by all N frames plus independent per-frame jitter."""
    bias = torch.randn((1, *shape[1:]), generator=gen, dtype=torch.float64) * (bias_fraction**0.5)
    jitter = torch.randn(tuple(shape), generator=gen, dtype=torch.float64) * ((1.0 - bias_fraction) ** 0.5)
    return sigma * (bias + jitter)


def perturb(
    params: BodyParams,
    level: float,
    *,
    model: BodyModel,
    seed: int = 0,
    config: PerturbConfig | None = None,
) -> BodyParams:
    """Estimator-like noisy copy of ``params`` (batch N = frames of one subject).

    model: the body model the parameters are for; its joint parts pick the hand joints and its
    expression bounds clamp the noisy expressions. Deterministic given ``seed``; ``level = 0``
    returns an exact copy.
    """
    c = config or PerturbConfig()
    if not level >= 0.0:  # also rejects NaN
        raise ValueError(f"level must be >= 0, got {level}")
    hand = (model.joint_part_ids[1:] == PART_NAMES.index("hand")).cpu()  # pose joints: all but the root
    if len(hand) != params.joints.shape[1]:
        raise ValueError(
            f"the {model.name} model has {len(hand)} pose joints, the params {params.joints.shape[1]}"
        )
    if level == 0.0:
        return params.map(lambda t: t.detach().clone())
    gen = torch.Generator().manual_seed(int(seed))
    n = params.batch_size
    sigma = torch.where(hand, c.hand_joint, c.body_joint).to(torch.float64)[None, :, None]
    b = c.bias_fraction
    joints = params.joints.double() + level * sigma * _noise(params.joints.shape, 1.0, b, gen)
    root = params.root_orient.double() + _noise((n, 3), level * c.root_orient, b, gen)
    transl = params.transl.double() + _noise((n, 3), level * c.transl, b, gen)
    expression = params.expression.double() + _noise(params.expression.shape, level * c.expression, b, gen)
    if model.expression_bounds is not None:
        expression = expression.clamp(*model.expression_bounds)
    shape_offset = torch.randn((1, params.shape.shape[1]), generator=gen, dtype=torch.float64)
    shape = params.shape.double() + level * c.shape * shape_offset
    out = BodyParams(root_orient=root, transl=transl, joints=joints, expression=expression, shape=shape)
    return BodyParams(**{k: v.to(getattr(params, k).dtype) for k, v in out.tensors().items()})
