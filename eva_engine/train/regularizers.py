"""Regularisers of the avatar itself (not of the image): ``RegularizerConfig`` and
``regularization(avatar, config, posed)``, added to the training loss each step. GART's (the
first five below) are 0 by default (EVA, GauHuman and 3DGS use none); ``gart+body`` sets GART's
PeopleSnapshot values (``profiles/people/people_1m.yaml``). ``thin`` and ``skinning`` keep an
avatar sound in poses and views the video never showed (``docs/novel-views.md``): ``thin`` is on by
default (the product's training), off in the paper's methods (``train/methods.py``: none of them has
it); ``skinning`` is off (no difference on the novel-pose benchmark). ``colour_offsets`` is off
(``docs/alignment.md``, "A ridge on the offsets": it removes the lids' specks but not their cost).

- ``knn_std``: for each Gaussian and its K nearest neighbours (canonical centres, itself
  included), the std of each attribute over the K, averaged: quaternion (raw), scales and opacity
  (activated), base and higher-order SH. The neighbour indices carry no gradient.
- ``field_tv`` / ``latent_tv``: total variation of the skinning field's correction grid / of its
  latent-bone channels; ``field_norm`` / ``latent_norm``: their mean per-voxel magnitude.
- ``small_scale``: mean over Gaussians of the squared largest scale.
- ``thin``: each Gaussian's standard deviation along the body surface's normal (at its template
  vertex, in canonical space) beyond ``thin_target``, in units of ``thin_target``, averaged. A
  Gaussian that grows along the training camera's rays (in front of a surface that faces the
  camera: along its normal) costs nothing in the training images and is a spike from the side.
  ``thin_part_weights`` scales it per part (body, hand, face), and ``thin_part_targets`` (metres,
  None: ``thin_target`` everywhere) sets each part's own free extent: a lid or a lip that the
  expression moves along the normal may need the depth the term takes away.
- ``skinning``: the squared distance between each Gaussian's skinning weights and the body
  model's at its template vertex, summed over joints and averaged (HUGS's and 3DGS-Avatar's
  prior): the weight-offset network may bend a weight, but a raised arm must not leave
  Gaussians behind that learnt to follow the spine. Mesh skinning only.
- ``colour_offsets``: ridge on the expression colours' offsets (``AvatarConfig.
  expression_colours``): the squared colour change each offset makes at its action's largest
  training coefficient, ``||SH_C0 delta_k||^2``, averaged over the (Gaussian, action) pairs the
  action recolours. Actions that move the same lid together (a blink and a squint) can learn
  large offsets that cancel on the training frames and not elsewhere; the ridge keeps the
  smallest offsets that explain the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from eva_engine.avatar import Avatar
from eva_engine.avatar.model import PosedGaussians
from eva_engine.geometry import knn_indices
from eva_engine.render import quat_to_rotmat
from eva_engine.render.sh import SH_C0


@dataclass(frozen=True)
class RegularizerConfig:
    """Weights of the regularisers (module docstring); knn: neighbours per Gaussian (with
    itself). ``lambda_thin`` 0.05 at 2 mm: the best of ``bench/novel_pose.py``'s rows (3 seeds,
    LPIPS-VGG -22% from 35/70 deg, -16% in far poses, -10% in near ones; ``docs/novel-views.md``)."""

    knn: int = 3
    lambda_knn_std: float = 0.0
    lambda_field_tv: float = 0.0
    lambda_latent_tv: float = 0.0
    lambda_field_norm: float = 0.0
    lambda_latent_norm: float = 0.0
    lambda_small_scale: float = 0.0
    lambda_thin: float = 0.05
    thin_target: float = 0.002
    thin_part_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    thin_part_targets: tuple[float, float, float] | None = None
    lambda_skinning: float = 0.0
    lambda_colour_offsets: float = 0.0

    def __post_init__(self) -> None:
        if len(self.thin_part_weights) != 3 or min(self.thin_part_weights) < 0:
            raise ValueError("thin_part_weights must be three weights >= 0 (body, hand, face)")
        if self.thin_part_targets is not None and (
            len(self.thin_part_targets) != 3 or min(self.thin_part_targets) <= 0
        ):
            raise ValueError("thin_part_targets must be three lengths > 0 (body, hand, face) or None")

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


def normal_extent(avatar: Avatar) -> Tensor:
    """[N] each Gaussian's standard deviation along its template vertex's rest-surface normal:
    sqrt(n^T R S^2 R^T n)."""
    g = avatar.gaussians
    normals = avatar.template_normals[g.vertex_ids]  # [N, 3]
    rot = quat_to_rotmat(g.splats["quats"])  # [N, 3, 3], columns: the Gaussian's axes
    along = (rot * normals[:, :, None]).sum(dim=1)  # [N, 3] n . axis_k
    return ((along * g.scales()) ** 2).sum(dim=-1).clamp_min(1e-20).sqrt()


def thin(
    avatar: Avatar,
    target: float,
    part_weights: tuple[float, float, float] = (1.0, 1.0, 1.0),
    part_targets: tuple[float, float, float] | None = None,
) -> Tensor:
    """Mean over Gaussians of relu(normal extent / target - 1), each with its part's weight and
    (``part_targets``) its part's target."""
    extent = normal_extent(avatar)  # [N]
    parts = avatar.gaussians.part_ids
    if part_targets is not None:
        target = extent.new_tensor(part_targets)[parts]  # type: ignore[assignment]
    excess = torch.relu(extent / target - 1.0)
    if tuple(part_weights) != (1.0, 1.0, 1.0):
        excess = excess * excess.new_tensor(part_weights)[parts]
    return excess.mean()


def skinning_prior(avatar: Avatar, weights: Tensor) -> Tensor:
    """Mean over Gaussians of sum_j (w - w_body)^2; weights: [N, J] as posed."""
    body = torch.exp(avatar.log_body_weights[avatar.gaussians.vertex_ids])
    body = body / body.sum(dim=-1, keepdim=True)
    return ((weights[:, : body.shape[1]] - body) ** 2).sum(dim=-1).mean()


def colour_offsets(avatar: Avatar) -> Tensor:
    """Mean over the (Gaussian, action) pairs an action recolours of ``||SH_C0 delta||^2``, the
    squared colour change of the offset ``delta`` (``splats.sh0_expression [N, K, 3]``); 0 for an
    avatar without expression colours."""
    g = avatar.gaussians
    offsets = g.splats.get("sh0_expression")
    if offsets is None or offsets.shape[1] == 0:
        return g.means.new_zeros(())
    reach = avatar.expression_reach[g.vertex_ids]  # [N, K]
    if not bool(reach.any()):
        return g.means.new_zeros(())
    change = (SH_C0 * offsets).square().sum(dim=-1)  # [N, K]
    return change[reach].mean()


def regularization(avatar: Avatar, config: RegularizerConfig, posed: PosedGaussians | None = None) -> Tensor:
    """The weighted sum of the active regularisers (a scalar; 0 when none is active); ``posed``:
    this step's posed Gaussians (their skinning weights, for ``lambda_skinning``)."""
    g = avatar.gaussians
    total = g.means.new_zeros(())
    if config.lambda_thin > 0:
        total = total + config.lambda_thin * thin(
            avatar, config.thin_target, config.thin_part_weights, config.thin_part_targets
        )
    if config.lambda_skinning > 0 and avatar.skinning_field is None:
        weights = (
            posed.weights if posed is not None and posed.weights is not None else avatar.skinning_weights()
        )
        total = total + config.lambda_skinning * skinning_prior(avatar, weights)
    if config.lambda_colour_offsets > 0:
        total = total + config.lambda_colour_offsets * colour_offsets(avatar)
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
