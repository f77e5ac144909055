"""GART's regularisers of the avatar itself (not of the image): ``RegularizerConfig`` and
``regularization(avatar, config)``, added to the training loss each step. All weights are 0 by
default (EVA, GauHuman and 3DGS use none); ``gart+body`` sets GART's PeopleSnapshot values
(``profiles/people/people_1m.yaml``).

- ``knn_std``: for each Gaussian and its K nearest neighbours (canonical centres, itself
  included), the std of each attribute over the K, averaged: quaternion (raw), scales and opacity
  (activated), base and higher-order SH. The neighbour indices carry no gradient.
- ``field_tv`` / ``latent_tv``: total variation of the skinning field's correction grid / of its
  latent-bone channels; ``field_norm`` / ``latent_norm``: their mean per-voxel magnitude.
- ``small_scale``: mean over Gaussians of the squared largest scale.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from eva_engine.avatar import Avatar
from eva_engine.geometry import knn_indices


@dataclass(frozen=True)
class RegularizerConfig:
    """Weights of the regularisers (module docstring); knn: neighbours per Gaussian (with
    itself)."""

    knn: int = 3
    lambda_knn_std: float = 0.0
    lambda_field_tv: float = 0.0
    lambda_latent_tv: float = 0.0
    lambda_field_norm: float = 0.0
    lambda_latent_norm: float = 0.0
    lambda_small_scale: float = 0.0

    @property
    def active(self) -> bool:
        return any(getattr(self, f.name) > 0 for f in fields(self) if f.name.startswith("lambda_"))


def knn_std(avatar: Avatar, k: int) -> Tensor:
    """Mean std of the Gaussians' attributes over each one's k nearest neighbours."""
    g = avatar.gaussians
    if len(g) < 2 or k < 2:
        return g.means.new_zeros(())
    idx = knn_indices(g.means, k)
    attributes = (
        g.splats["quats"],
        g.scales(),
        g.opacities()[:, None],
        g.splats["sh0"].flatten(1),
        g.splats["shN"].flatten(1),
    )
    terms = [a[idx].std(dim=1).mean() for a in attributes if a.shape[1] > 0]
    return torch.stack(terms).sum()


def regularization(avatar: Avatar, config: RegularizerConfig) -> Tensor:
    """The weighted sum of the active regularisers (a scalar; 0 when none is active)."""
    g = avatar.gaussians
    total = g.means.new_zeros(())
    if config.lambda_knn_std > 0:
        total = total + config.lambda_knn_std * knn_std(avatar, config.knn)
    if config.lambda_small_scale > 0:
        total = total + config.lambda_small_scale * (g.scales().amax(dim=-1) ** 2).mean()
    field = avatar.skinning_field
    if field is not None:
        if config.lambda_field_tv > 0 or config.lambda_latent_tv > 0:
            tv, latent_tv = field.total_variation()
            total = total + config.lambda_field_tv * tv + config.lambda_latent_tv * latent_tv
        if config.lambda_field_norm > 0 or config.lambda_latent_norm > 0:
            norm, latent_norm = field.magnitude()
            total = total + config.lambda_field_norm * norm + config.lambda_latent_norm * latent_norm
    return total
