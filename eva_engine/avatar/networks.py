"""The two small MLPs of EVA §3.1 and their positional encoding.

- ``LBSWeightOffsets``: gamma(p_c) -> per-joint offsets w' [N, J]; the skinning weights are
  w = softmax(log(w_body + eps) + w') (``blend_skinning_weights``).
- ``PoseRefiner``: theta = theta_in (x) f(theta_in). We follow EVA's official code (GauHuman's
  ``BodyPoseRefiner``, one network per part): for each part (body, hands, face) an MLP maps the
  part's input joint rotations (axis-angle, flattened) to a small per-joint rotation delta, and
  the refined rotation of joint j is R(theta_j) R(delta_j) (rotation composition, the "(x)").
  The root orientation and translation are not refined.

Both last layers start uniform in +-``out_init`` (1e-5) with zero bias, so at initialisation the
skinning is the body model's and the pose is the input pose (to ~1e-5).
"""

from __future__ import annotations

import math

import roma
import torch
from torch import Tensor, nn

from eva_engine.body.model import PART_NAMES
from eva_engine.layers import seeded_layer


def positional_encoding(x: Tensor, frequencies: int) -> Tensor:
    """NeRF's gamma: [..., D] -> [..., D (1 + 2 L)] = (x, sin(2^k pi x), cos(2^k pi x)), k < L."""
    if frequencies == 0:
        return x
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * math.pi
    xb = x[..., None, :] * scales[:, None]  # [..., L, D]
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1).flatten(-2)
    return torch.cat([x, enc], dim=-1)


def make_mlp(
    d_in: int, d_out: int, width: int, depth: int, out_init: float, generator: torch.Generator
) -> nn.Sequential:
    """``depth`` hidden ReLU layers of ``width`` (torch's default initialisation); last layer
    uniform(+-out_init), bias 0; every draw from ``generator``."""
    layers: list[nn.Module] = []
    d = d_in
    for _ in range(depth):
        layers += [seeded_layer(nn.Linear, d, width, generator=generator), nn.ReLU()]
        d = width
    last = seeded_layer(nn.Linear, d, d_out, generator=generator)
    with torch.no_grad():
        nn.init.uniform_(last.weight, -out_init, out_init, generator=generator)
        nn.init.zeros_(last.bias)
    layers.append(last)
    return nn.Sequential(*layers)


class LBSWeightOffsets(nn.Module):
    """f_w: canonical centres [N, 3] -> LBS weight offsets [N, J] (EVA eq. for w_k).
    generator: the initial weights' random draws (None: a generator seeded 0)."""

    def __init__(
        self,
        num_joints: int,
        frequencies: int,
        width: int,
        depth: int,
        out_init: float,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.frequencies = frequencies
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.mlp = make_mlp(3 * (1 + 2 * frequencies), num_joints, width, depth, out_init, generator)

    def forward(self, means: Tensor) -> Tensor:
        return self.mlp(positional_encoding(means, self.frequencies))


def blend_skinning_weights(base: Tensor, offsets: Tensor | None, eps: float = 1e-8) -> Tensor:
    """w = softmax(log(base + eps) + offsets). base: [N, J] rows summing to 1; offsets: [N, J] or
    None (then w = base renormalised with eps, i.e. the body model's weights)."""
    logits = torch.log(base + eps)
    if offsets is not None:
        logits = logits + offsets
    return torch.softmax(logits, dim=-1)


class PoseRefiner(nn.Module):
    """Per-part pose correction (see the module docstring).

    joint_part_ids: [P] part index of each pose joint (``model.pose_joint_names`` order).
    forward: joints [B, P, 3] axis-angle -> refined joints [B, P, 3].
    generator: the initial weights' random draws (None: a generator seeded 0).
    """

    joint_part_ids: Tensor

    def __init__(
        self,
        joint_part_ids: Tensor,
        width: int,
        depth: int,
        out_init: float,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.register_buffer("joint_part_ids", joint_part_ids.to(torch.int64).clone())
        self.mlps = nn.ModuleDict()
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        for i, part in enumerate(PART_NAMES):
            n = int((self.joint_part_ids == i).sum())
            if n:
                self.mlps[part] = make_mlp(3 * n, 3 * n, width, depth, out_init, generator)

    def deltas(self, joints: Tensor) -> Tensor:
        """[B, P, 3] predicted rotation deltas (axis-angle)."""
        out = torch.zeros_like(joints)
        for i, part in enumerate(PART_NAMES):
            if part not in self.mlps:
                continue
            idx = torch.nonzero(self.joint_part_ids == i).squeeze(1)
            x = joints[:, idx]
            out[:, idx] = self.mlps[part](x.flatten(1)).view_as(x)
        return out

    def forward(self, joints: Tensor) -> Tensor:
        return roma.rotvec_composition([joints, self.deltas(joints)])
