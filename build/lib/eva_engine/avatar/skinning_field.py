"""GART's skinning (Lei et al., CVPR 2024; ``JiahuiLei/GART``, ``lib_gart/voxel_deformer.py`` and
``lib_gart/model.py``): a learnable field of LBS weights, and latent bones.

- ``SkinningField``: a voxel grid of per-bone weights over the canonical body, read by trilinear
  interpolation at each Gaussian's canonical centre. The grid spans the template's bounding box
  (centred, half-size 1.2 x its largest half-extent) with the depth axis (z: the subject faces
  +Z) four times shorter than x and y, so (D, H, W) = (res/4, res, res). Its fixed base comes from
  the body model's vertex weights: each node averages its 30 nearest template vertices' weights
  by inverse distance, then 30 diffusion sweeps (w <- 0.7 w + 0.3 mean of the 6 neighbours, on
  interior nodes, weights renormalised to sum 1 after each) smooth it. A learnable correction
  grid (zero at the start) is added to it, with no normalisation afterwards, as in GART.
  ``latent_bones`` extra channels (a constant 1e-4 at the start) hold the latent bones' weights.
- ``LatentBones``: K extra bones for what the skeleton does not move (hair, loose clothes): an MLP
  (4 x 256, LeakyReLU) maps the pose (every joint rotation but the root's) to a rotation
  (quaternion) and a translation per bone, the identity at the start. Each latent bone is a
  child of the root: its transform is the root's times its own (``Avatar.pose``).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor, nn

from eva_engine.layers import seeded_layer
from eva_engine.render import quat_to_rotmat

DEPTH_RATIO = 4  # the grid's depth axis (z) spans this many times less than x and y


def grid_weights_from_vertices(
    nodes: Tensor, vertices: Tensor, vertex_weights: Tensor, neighbours: int = 30
) -> Tensor:
    """[M, J] weights at ``nodes [M, 3]``: the inverse-distance average of the weights
    ``vertex_weights [V, J]`` of the ``neighbours`` nearest ``vertices [V, 3]`` (distances clamped
    to [1e-4, 1])."""
    k = min(neighbours, vertices.shape[0])
    tree = cKDTree(vertices.detach().cpu().double().numpy())
    dist, idx = tree.query(nodes.cpu().double().numpy(), k=k)
    dist, idx = dist.reshape(len(nodes), k), idx.reshape(len(nodes), k)
    inv = 1.0 / np.clip(dist, 1e-4, 1.0)
    ws = torch.from_numpy(inv / inv.sum(axis=1, keepdims=True)).to(vertex_weights)
    idx = torch.from_numpy(idx)
    out = vertex_weights.new_zeros(len(nodes), vertex_weights.shape[1])
    for i in range(k):  # one neighbour at a time: [M, k, J] at once would be ~1 GB
        out += ws[:, i, None] * vertex_weights[idx[:, i]]
    return out


def diffuse(grid: Tensor, steps: int = 30, keep: float = 0.7) -> Tensor:
    """``steps`` Jacobi sweeps on the interior of ``grid [1, J, D, H, W]``: w <- keep w + (1 -
    keep) mean(6 face neighbours), each followed by renormalising the channels to sum 1."""
    w = grid.clone()
    for _ in range(steps):
        mean = (
            w[:, :, :-2, 1:-1, 1:-1]
            + w[:, :, 2:, 1:-1, 1:-1]
            + w[:, :, 1:-1, :-2, 1:-1]
            + w[:, :, 1:-1, 2:, 1:-1]
            + w[:, :, 1:-1, 1:-1, :-2]
            + w[:, :, 1:-1, 1:-1, 2:]
        ) / 6.0
        w[:, :, 1:-1, 1:-1, 1:-1] = keep * w[:, :, 1:-1, 1:-1, 1:-1] + (1.0 - keep) * mean
        w = w / w.sum(dim=1, keepdim=True).clamp_min(1e-12)
    return w


def _total_variation(grid: Tensor) -> Tensor:
    return (
        (grid[:, :, 1:] - grid[:, :, :-1]).abs().mean()
        + (grid[:, :, :, 1:] - grid[:, :, :, :-1]).abs().mean()
        + (grid[:, :, :, :, 1:] - grid[:, :, :, :, :-1]).abs().mean()
    ) / 3.0


class SkinningField(nn.Module):
    """Learnable LBS-weight grid (module docstring).

    template: [V, 3] canonical template vertices; vertex_weights: [V, J] their LBS weights;
    resolution: grid side in x and y (z has resolution / 4); latent_bones: extra weight channels.
    forward: canonical points [N, 3] -> weights [N, J + latent_bones] (not normalised).
    """

    base: Tensor
    center: Tensor

    def __init__(
        self, template: Tensor, vertex_weights: Tensor, resolution: int = 64, latent_bones: int = 0
    ) -> None:
        super().__init__()
        if resolution < 2 * DEPTH_RATIO:
            raise ValueError(f"resolution must be >= {2 * DEPTH_RATIO}, got {resolution}")
        template = template.detach().float().cpu()
        lo, hi = template.amin(dim=0), template.amax(dim=0)
        self.register_buffer("center", (lo + hi) / 2.0, persistent=False)
        self.half_size = 1.2 * float((hi - lo).amax()) / 2.0
        d, h, w = resolution // DEPTH_RATIO, resolution, resolution
        z, y, x = torch.meshgrid(*(torch.linspace(-1.0, 1.0, n) for n in (d, h, w)), indexing="ij")
        nodes = torch.stack([x, y, z / DEPTH_RATIO], dim=-1).reshape(-1, 3) * self.half_size + self.center
        j = vertex_weights.shape[1]
        base = grid_weights_from_vertices(nodes, template, vertex_weights.detach().float().cpu())
        # Derived from the body model and the shape: rebuilt with the avatar, not saved.
        self.register_buffer("base", diffuse(base.T.reshape(1, j, d, h, w)), persistent=False)
        self.correction = nn.Parameter(torch.zeros_like(self.base))
        shape = (1, latent_bones, d, h, w)
        self.latent = nn.Parameter(torch.full(shape, 1e-4)) if latent_bones else None

    def grid(self) -> Tensor:
        """[1, J + K, D, H, W]: the field's current weights."""
        grids = [self.base + self.correction] + ([self.latent] if self.latent is not None else [])
        return torch.cat(grids, dim=1)

    def forward(self, points: Tensor) -> Tensor:
        x = (points - self.center) / self.half_size * points.new_tensor([1.0, 1.0, DEPTH_RATIO])
        grid = self.grid().to(points.dtype)
        # Trilinear (grid_sample's "bilinear" on a 5-D input); outside the box: the border value.
        out = F.grid_sample(grid, x.view(1, -1, 1, 1, 3), align_corners=True, padding_mode="border")
        return out.view(grid.shape[1], -1).T

    def total_variation(self) -> tuple[Tensor, Tensor]:
        """(TV of the correction grid, TV of the latent-bone channels; 0 without them)."""
        latent = _total_variation(self.latent) if self.latent is not None else self.correction.new_zeros(())
        return _total_variation(self.correction), latent

    def magnitude(self) -> tuple[Tensor, Tensor]:
        """Mean over voxels of the norm over channels: (correction, latent-bone channels)."""
        zero = self.correction.new_zeros(())
        latent = self.latent.norm(dim=1).mean() if self.latent is not None else zero
        return self.correction.norm(dim=1).mean(), latent


class LatentBones(nn.Module):
    """K latent bones driven by the pose (module docstring).

    pose_dim: length of the flattened non-root joint rotations; forward: joints [1, P, 3]
    axis-angle (3 P == pose_dim) -> [K, 4, 4] transforms relative to the root bone (the identity
    at the start, to ~1e-3). generator: the initial weights' draws (None: a generator seeded 0).
    """

    def __init__(
        self,
        pose_dim: int,
        bones: int,
        width: int = 256,
        depth: int = 4,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        layers: list[nn.Module] = []
        d = pose_dim
        for _ in range(depth):
            layers += [seeded_layer(nn.Linear, d, width, generator=generator), nn.LeakyReLU()]
            d = width
        self.mlp = nn.Sequential(*layers)
        self.head = nn.utils.skip_init(nn.Linear, d, 7 * bones, bias=False)
        with torch.no_grad():
            self.head.weight.copy_(torch.randn(self.head.weight.shape, generator=generator) * 1e-3)
        self.bones = bones

    def forward(self, joints: Tensor) -> Tensor:
        out = self.head(self.mlp(joints.reshape(1, -1))).view(self.bones, 7)
        quats = out[:, :4] + out.new_tensor([1.0, 0.0, 0.0, 0.0])
        quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        top = torch.cat([quat_to_rotmat(quats), out[:, 4:, None]], dim=-1)  # [K, 3, 4]
        bottom = out.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(self.bones, 1, 4)
        return torch.cat([top, bottom], dim=1)
