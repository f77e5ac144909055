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

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from eva_engine.avatar import Avatar


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
        return any(
            w > 0
            for w in (
                self.lambda_knn_std,
                self.lambda_field_tv,
                self.lambda_latent_tv,
                self.lambda_field_norm,
                self.lambda_latent_norm,
                self.lambda_small_scale,
            )
        )


def knn_indices(points: Tensor, k: int) -> Tensor:
    """[N, k] indices of each point's k nearest points, itself first (exact, no gradient)."""
    x = points.detach().cpu().double().numpy()
    k = min(k, len(x))
    _, idx = cKDTree(x).query(x, k=k)
    return torch.from_numpy(np.asarray(idx).reshape(len(x), k)).to(points.device)


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
