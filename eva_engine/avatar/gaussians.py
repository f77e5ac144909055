"""``CanonicalGaussians``: the avatar's 3D Gaussians in the canonical (rest) space of its body.

Learnable tensors live in ``splats`` (a ``ParameterDict``, gsplat's layout) so density-control
strategies can replace them together with their optimizer state:

    means [N, 3] (metres, canonical), scales [N, 3] (log of standard deviations),
    quats [N, 4] (w, x, y, z, any norm), opacities [N] (logits),
    sh0 [N, 1, 3] (DC spherical-harmonics term), shN [N, K - 1, 3] (higher degrees, K = (d + 1)^2),
    and optionally sh0_expression [N, A, 3] (DC offsets per revealing expression action,
    ``avatar/expression_colours.py``).

Per-Gaussian tensors that are not learned (``PER_GAUSSIAN_BUFFERS``) follow every clone, split
and prune too: ``part_ids [N]`` (index into ``PART_NAMES``, inherited by children) and
``vertex_ids [N]`` (the nearest template vertex, whose skinning weights and expression offsets
the Gaussian borrows; refreshed as the means move).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from eva_engine.avatar.eye_binding import EyeOpening, attach_to_eyeballs
from eva_engine.body.model import nearest_vertex_index
from eva_engine.geometry import mean_neighbour_distance, quat_from_z
from eva_engine.memo import InferenceMemo
from eva_engine.render.sh import num_sh_bases

PER_GAUSSIAN_BUFFERS = ("part_ids", "vertex_ids")
SPLAT_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")
OPTIONAL_SPLAT_NAMES = ("sh0_expression",)


class CanonicalGaussians(nn.Module):
    """Canonical Gaussians tied to a body template (see the module docstring).

    template_vertices: [V, 3] rest-pose vertices of the subject's body (shape applied, no
    expression); template_part_ids: [V] part index per vertex.
    """

    part_ids: Tensor
    vertex_ids: Tensor
    template_vertices: Tensor
    template_part_ids: Tensor

    def __init__(
        self,
        splats: dict[str, Tensor],
        part_ids: Tensor,
        vertex_ids: Tensor,
        template_vertices: Tensor,
        template_part_ids: Tensor,
    ) -> None:
        super().__init__()
        missing = [k for k in SPLAT_NAMES if k not in splats]
        if missing:
            raise ValueError(f"splats lack {missing}")
        unknown = set(splats) - set(SPLAT_NAMES) - set(OPTIONAL_SPLAT_NAMES)
        if unknown:
            raise ValueError(f"unknown splats {sorted(unknown)}")
        names = [k for k in (*SPLAT_NAMES, *OPTIONAL_SPLAT_NAMES) if k in splats]
        n = splats["means"].shape[0]
        for k in names:
            if splats[k].shape[0] != n:
                raise ValueError(f"splats[{k!r}] has {splats[k].shape[0]} rows, expected {n}")
        if part_ids.shape != (n,) or vertex_ids.shape != (n,):
            raise ValueError(f"part_ids and vertex_ids must be [{n}]")
        self.splats = nn.ParameterDict({k: nn.Parameter(splats[k].detach().clone()) for k in names})
        self.register_buffer("part_ids", part_ids.to(torch.int64).clone())
        self.register_buffer("vertex_ids", vertex_ids.to(torch.int64).clone())
        self.register_buffer("template_vertices", template_vertices.detach().clone())
        self.register_buffer("template_part_ids", template_part_ids.to(torch.int64).clone())
        self._sh_memo = InferenceMemo()
        # The eyes' openings (``avatar/eye_binding.py``; set by the avatar with
        # ``AvatarConfig.eye_binding``): Gaussians seen through one attach to its eyeball.
        self.eye_openings: list[EyeOpening] = []

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_template(
        cls,
        template_vertices: Tensor,
        template_part_ids: Tensor,
        seed_mask: Tensor | None = None,
        sh_degree: int = 3,
        init_opacity: float = 0.1,
        max_gaussians: int | None = None,
        generator: torch.Generator | None = None,
        normals: Tensor | None = None,
        normal_ratio: float = 1.0,
    ) -> CanonicalGaussians:
        """One Gaussian per template vertex (those in ``seed_mask [V]``; at most ``max_gaussians``
        of them, a random subset drawn with ``generator``) with the 3DGS initial scale (mean
        distance to the 3 nearest seeds) and a mid-grey colour: isotropic with the identity
        rotation, or with ``normals [V, 3]`` (unit vertex normals) and ``normal_ratio`` < 1 a
        disc: its local z on the normal, ``normal_ratio`` times thinner along it."""
        v = template_vertices.shape[0]
        ids = torch.arange(v) if seed_mask is None else torch.nonzero(seed_mask.cpu()).squeeze(1)
        if max_gaussians is not None and ids.numel() > max_gaussians:
            perm = torch.randperm(ids.numel(), generator=generator)[:max_gaussians]
            ids = ids[perm.sort().values]
        ids = ids.to(template_vertices.device)
        means = template_vertices[ids].detach().clone()
        scale = mean_neighbour_distance(means, 3, exact=False).clamp(1e-4, 0.05)
        n = means.shape[0]
        k = num_sh_bases(sh_degree)
        log_scales = torch.log(scale)[:, None].expand(n, 3).clone()
        quats = means.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).clone()
        if normals is not None and normal_ratio < 1.0:
            quats = quat_from_z(normals[ids].to(means))
            log_scales[:, 2] += math.log(normal_ratio)
        splats = {
            "means": means,
            "scales": log_scales,
            "quats": quats,
            "opacities": means.new_full((n,), math.log(init_opacity / (1.0 - init_opacity))),
            "sh0": means.new_zeros(n, 1, 3),  # rgb_to_sh(0.5) == 0: mid-grey
            "shN": means.new_zeros(n, k - 1, 3),
        }
        return cls(splats, template_part_ids[ids], ids, template_vertices, template_part_ids)

    # -- views -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.splats["means"].shape[0])

    @property
    def means(self) -> Tensor:
        return self.splats["means"]

    @property
    def sh_degree(self) -> int:
        """Highest SH degree stored."""
        return int(math.isqrt(self.splats["shN"].shape[1] + 1)) - 1

    def scales(self) -> Tensor:
        """[N, 3] standard deviations (exp of the log-scales)."""
        return torch.exp(self.splats["scales"])

    @torch.no_grad()
    def clamp_scales(self, max_per_part: Tensor) -> None:
        """Project every standard deviation under its part's bound: ``max_per_part [P]`` metres
        per ``part_ids`` value (in place: the optimizer keeps its state)."""
        bound = torch.log(max_per_part.to(self.splats["scales"]))[self.part_ids]
        scales = self.splats["scales"]
        scales.copy_(torch.minimum(scales, bound[:, None]))

    def opacities(self) -> Tensor:
        """[N] opacities in (0, 1)."""
        return torch.sigmoid(self.splats["opacities"])

    def sh(self) -> Tensor:
        """[N, K, 3] all SH coefficients (one tensor made once between renders of a trained
        avatar, ``eva_engine/memo.py``: a copy of every coefficient per frame otherwise)."""
        sh0, shn = self.splats["sh0"], self.splats["shN"]
        return self._sh_memo.get((sh0, shn), lambda: torch.cat([sh0, shn], dim=1))

    def add_expression_offsets(self, num_actions: int) -> None:
        """Give every Gaussian zero colour offsets for ``num_actions`` expression actions (the
        ``sh0_expression`` splat), unless it has them; before the optimizers are made."""
        if "sh0_expression" not in self.splats:
            sh0 = self.splats["sh0"]
            self.splats["sh0_expression"] = nn.Parameter(sh0.new_zeros(len(self), num_actions, 3))

    def buffers_per_gaussian(self) -> dict[str, Tensor]:
        return {name: getattr(self, name) for name in PER_GAUSSIAN_BUFFERS}

    def set_buffer(self, name: str, value: Tensor) -> None:
        """Replace one per-Gaussian buffer (its row count follows the splats)."""
        if name not in PER_GAUSSIAN_BUFFERS:
            raise KeyError(f"{name!r} is not a per-Gaussian buffer ({PER_GAUSSIAN_BUFFERS})")
        setattr(self, name, value)

    # -- template relations ------------------------------------------------------------------
    @torch.no_grad()
    def refresh_vertex_ids(self) -> None:
        """Re-attach every Gaussian to its nearest template vertex (after the means moved), or,
        seen through an eye's opening (``eye_openings``), to its eyeball."""
        means, template = self.means.detach(), self.template_vertices
        self.vertex_ids = nearest_vertex_index(means, template)
        if self.eye_openings:
            self.vertex_ids = attach_to_eyeballs(means, self.vertex_ids, template, self.eye_openings)

    @torch.no_grad()
    def template_distance(self, same_part: bool = False) -> Tensor:
        """[N] canonical distance of each mean to the nearest template vertex (of any part, or
        with ``same_part`` of the Gaussian's own part)."""
        means = self.means.detach()
        if not same_part:
            idx = nearest_vertex_index(means, self.template_vertices)
            return (means - self.template_vertices[idx]).norm(dim=-1)
        out = means.new_full((means.shape[0],), float("inf"))
        for part in self.part_ids.unique().tolist():
            sel = self.part_ids == part
            verts = self.template_vertices[self.template_part_ids == part]
            if verts.shape[0] == 0:
                continue
            idx = nearest_vertex_index(means[sel], verts)
            out[sel] = (means[sel] - verts[idx]).norm(dim=-1)
        return out
