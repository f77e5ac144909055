"""``Avatar``: canonical Gaussians + body model + the two MLPs -> posed, rendered images.

The avatar belongs to one subject: its canonical space is the body model's rest pose with the
subject's ``shape`` and the template's expression (none, or the training frames' median:
``AvatarConfig.template_expression``). Posing a frame (``pose``):

1. pose refinement (``PoseRefiner``) of the input joint rotations;
2. the body model gives the rest -> posed joint transforms for the refined pose, with the
   avatar's shape (the ``shape`` of the input params is ignored: the avatar is one person);
3. expression (and any shape blendshape) offsets: each Gaussian moves with its nearest template
   vertex, ``canonical(params)[v] - template[v]`` (Anny's jaw and eyelids move through
   blendshapes, not bones), and with ``AvatarConfig.expression_frames`` also turns and scales
   with the skin around that vertex (``avatar/surface_frames.py``);
4. skinning with w = softmax(log(w_body[v] + eps) + f_w(gamma(p_c))) (``skin_gaussians``), or
   with GART's learnable weight field and latent bones (``AvatarConfig.skinning == "field"``,
   ``avatar/skinning_field.py``);
5. colours from SH evaluated for the view direction rotated back into canonical space; with
   ``AvatarConfig.expression_colours`` the DC term first takes the expression's colour offsets
   (``avatar/expression_colours.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from eva_engine.avatar.config import AvatarConfig
from eva_engine.avatar.expression_colours import (
    action_reach,
    expression_range,
    expression_sh0,
    revealing_actions,
)
from eva_engine.avatar.eye_binding import eye_openings
from eva_engine.avatar.gaussians import CanonicalGaussians
from eva_engine.avatar.networks import LBSWeightOffsets, PoseRefiner, blend_log_skinning_weights
from eva_engine.avatar.skinning import skin_gaussians, sparse_weights
from eva_engine.avatar.skinning_field import LatentBones, SkinningField
from eva_engine.avatar.surface_frames import follow_skin, normals_and_areas
from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams
from eva_engine.geometry import vertex_normals
from eva_engine.memo import InferenceMemo
from eva_engine.render import RasterConfig, RenderOutput, eval_sh, rasterize
from eva_engine.render.camera import Camera


@dataclass
class PosedGaussians:
    """Gaussians of one frame in world space (N Gaussians, K SH coefficients).

    means: [N, 3]; quats: [N, 4]; scales: [N, 3] (linear); opacities: [N]; sh: [N, K, 3];
    rotations: [N, 3, 3] canonical -> world rotation of each Gaussian; params: the refined
    body parameters used; weights: [N, J] the skinning weights used (J joints, plus any latent
    bones).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    rotations: Tensor
    params: BodyParams
    weights: Tensor | None = None


class Avatar(nn.Module):
    """A drivable Gaussian avatar (see the module docstring).

    body: the body model (its name and the avatar's ``shape [S]`` are its identity);
    gaussians: canonical Gaussians over ``body.canonical(shape)`` with ``expression [E]`` (None:
    zero; ``AvatarConfig.template_expression``); generator: the MLPs' initial weights' random
    draws (None: a generator seeded 0).
    """

    shape: Tensor

    def __init__(
        self,
        body: BodyModel,
        gaussians: CanonicalGaussians,
        shape: Tensor,
        config: AvatarConfig,
        generator: torch.Generator | None = None,
        expression: Tensor | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.body = body
        self.gaussians = gaussians
        self.register_buffer("shape", shape.detach().to(body.dtype).reshape(-1).clone())
        # [E] the expression of the face the Gaussians sit on (``gaussians.template_vertices``);
        # a frame moves them by its expression's difference from it.
        if expression is None:
            expression = torch.zeros(len(body.expression_names))
        expression = expression.detach().to(shape.device, body.dtype).reshape(-1).clone()
        self.register_buffer("template_expression", expression)
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.weight_offsets = (
            LBSWeightOffsets(
                body.num_joints,
                config.pe_frequencies,
                config.mlp_width,
                config.mlp_depth,
                config.mlp_out_init,
                generator,
            )
            if config.weight_offsets
            else None
        )
        parts = body.joint_part_ids[1:]  # pose joints: all but the root
        self.pose_refiner = (
            PoseRefiner(parts, config.mlp_width, config.mlp_depth, config.mlp_out_init, generator)
            if config.pose_refine
            else None
        )
        self.skinning_field = (
            SkinningField(
                gaussians.template_vertices,
                body.skinning_weights,
                config.field_resolution,
                config.latent_bones,
            ).to(gaussians.template_vertices.device)
            if config.skinning == "field"
            else None
        )
        self.latent_bones = (
            LatentBones(3 * len(parts), config.latent_bones, generator=generator)
            if config.latent_bones
            else None
        )
        # log(w_body + eps) per body vertex [V, J]: gathered per Gaussian, not recomputed per step.
        self.register_buffer(
            "log_body_weights", torch.log(body.skinning_weights + config.lbs_eps), persistent=False
        )
        # Unit normals of the subject's rest surface [V, 3] (the regularisers' "thin along the
        # normal"): derived from the template, so not saved.
        normals = vertex_normals(gaussians.template_vertices.detach().cpu(), body.faces.cpu())
        self.register_buffer(
            "template_normals", torch.from_numpy(normals).to(gaussians.template_vertices), persistent=False
        )
        if config.expression_colours:
            actions = revealing_actions(list(body.expression_names), config.expression_colour_actions)
            gaussians.add_expression_offsets(len(actions))
            # Derived from the body model, so not saved: [K] the actions, [V, K] what they move.
            self.register_buffer(
                "expression_actions", torch.tensor(actions, dtype=torch.long), persistent=False
            )
            reach = action_reach(body, self.shape, actions, spread=config.expression_colour_spread)
            self.register_buffer("expression_reach", reach, persistent=False)
            # [K] r_k, set from the training frames (``set_expression_range``) and saved.
            self.register_buffer("expression_range", torch.ones(len(actions), dtype=body.dtype))
        if config.eye_binding and hasattr(body, "eye_vertices"):
            skin, eyeballs = body.eye_vertices()
            gaussians.eye_openings = eye_openings(gaussians.template_vertices, body.faces, skin, eyeballs)
        self.active_sh_degree = gaussians.sh_degree
        self._weights_memo = InferenceMemo()
        self._sparse_weights_memo = InferenceMemo()
        self._posed_memo = InferenceMemo()
        self._rest_surface_memo = InferenceMemo()

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def create(
        cls,
        body: BodyModel,
        shape: Tensor,
        config: AvatarConfig | None = None,
        seed: int = 0,
        generator: torch.Generator | None = None,
        expression: Tensor | None = None,
    ) -> Avatar:
        """A fresh avatar seeded on the surface vertices of ``body.canonical(shape)``: ``seed``
        draws the subset of seed vertices, ``generator`` the MLPs' initial weights (None: a
        generator seeded ``seed``; pass one to draw further initial weights after them);
        ``expression [E]``: the template's expression (``AvatarConfig.template_expression``;
        None: zero)."""
        config = config or AvatarConfig()
        template = template_vertices(body, shape, expression)
        normals = None
        if config.init_normal_ratio < 1.0:
            normals = torch.from_numpy(vertex_normals(template.cpu(), body.faces.cpu())).to(template)
        gaussians = CanonicalGaussians.from_template(
            template,
            body.part_ids,
            seed_mask=getattr(body, "surface_vertex_mask", None),
            sh_degree=config.sh_degree,
            init_opacity=config.init_opacity,
            max_gaussians=config.init_max_gaussians,
            generator=torch.Generator().manual_seed(seed),
            normals=normals,
            normal_ratio=config.init_normal_ratio,
        )
        generator = generator if generator is not None else torch.Generator().manual_seed(seed)
        return cls(body, gaussians, shape, config, generator, expression)

    def networks(self) -> dict[str, nn.Module]:
        """The learnable parts besides the Gaussians, by name (what ``save_avatar`` stores)."""
        named = {
            "weight_offsets": self.weight_offsets,
            "pose_refiner": self.pose_refiner,
            "skinning_field": self.skinning_field,
            "latent_bones": self.latent_bones,
        }
        return {name: m for name, m in named.items() if m is not None}

    def mlp_parameters(self) -> list[nn.Parameter]:
        return [p for m in self.networks().values() for p in m.parameters()]

    # -- posing ------------------------------------------------------------------------------
    def subject_params(self, params: BodyParams) -> BodyParams:
        """``params`` with the avatar's shape (batch preserved) on the avatar's device/dtype."""
        params = params.to(device=self.shape.device, dtype=self.shape.dtype)
        return BodyParams(
            root_orient=params.root_orient,
            transl=params.transl,
            joints=params.joints,
            expression=params.expression,
            shape=self.shape.expand(params.batch_size, -1),
        )

    def refine_pose(self, params: BodyParams) -> BodyParams:
        params = self.subject_params(params)
        if self.pose_refiner is None:
            return params
        return BodyParams(
            root_orient=params.root_orient,
            transl=params.transl,
            joints=self.pose_refiner(params.joints),
            expression=params.expression,
            shape=params.shape,
        )

    def skinning_weights(self) -> Tensor:
        """[N, J] per-Gaussian LBS weights (body-model weights of the nearest vertex + offsets),
        or [N, J + K] read from the skinning field (K latent bones). Without autograd (rendering a
        trained avatar) they are computed once and reused until a tensor they depend on changes
        (``eva_engine/memo.py``)."""
        g = self.gaussians
        inputs = [g.means, g.vertex_ids, self.log_body_weights]
        for module in (self.weight_offsets, self.skinning_field):
            if module is not None:
                inputs += list(module.parameters())
        return self._weights_memo.get(inputs, self._compute_skinning_weights)

    def _compute_skinning_weights(self) -> Tensor:
        g = self.gaussians
        if self.skinning_field is not None:
            return self.skinning_field(g.means)
        if self.weight_offsets is not None:
            means = g.means.detach() if self.config.detach_weight_inputs else g.means
            return self.weight_offsets.skinning_weights(
                means, self.log_body_weights, g.vertex_ids, bf16=self.config.weight_mlp_bf16
            )
        return blend_log_skinning_weights(self.log_body_weights[g.vertex_ids], None)

    def pose(self, params: BodyParams) -> PosedGaussians:
        """Pose the Gaussians for one frame: ``params`` with batch 1. Without autograd the last
        pose is kept while the avatar's tensors and the values of ``params`` stay the same: a
        render that changes only the camera (the page's view slider) skips the posing. Read the
        result, never modify it in place."""
        if params.batch_size != 1:
            raise ValueError(f"pose one frame at a time, got a batch of {params.batch_size}")
        own = [*self.parameters(), *self.buffers()]
        return self._posed_memo.get(own, lambda: self._pose(params), key=list(params.tensors().values()))

    def _pose(self, params: BodyParams) -> PosedGaussians:
        g = self.gaussians
        refined = self.refine_pose(params)
        rest, transforms = self.body.rest_and_transforms(refined)
        rest, transforms = rest[0], transforms[0]  # [V, 3] with this frame's expression, [J, 4, 4]
        if self.latent_bones is not None:  # children of the root: [J + K, 4, 4]
            transforms = torch.cat([transforms, transforms[0] @ self.latent_bones(refined.joints)])
        weights = self.skinning_weights()
        rest_surface = None  # the template's normals and areas, kept between renders
        if self.config.expression_frames and not torch.is_grad_enabled():
            template, faces = g.template_vertices, self.body.faces
            rest_surface = self._rest_surface_memo.get(
                [template, faces], lambda: normals_and_areas(template, faces)
            )
        means, quats, scales, carried, turns = follow_skin(
            g.means,
            g.splats["quats"],
            g.scales(),
            g.vertex_ids,
            g.template_vertices,
            rest,
            self.body.faces,
            frames=self.config.expression_frames,
            rest_surface=rest_surface,
        )
        blend = weights  # a render's blend reads the few bones each Gaussian follows
        if not torch.is_grad_enabled():
            blend = self._sparse_weights_memo.get([weights], lambda: sparse_weights(weights))
        means, quats, rot = skin_gaussians(means, quats, blend, transforms)
        if len(carried):  # view directions undo the turn too
            rot = rot.index_copy(0, carried, rot[carried] @ turns)
        sh = self.colours(refined)
        return PosedGaussians(means, quats, scales, g.opacities(), sh, rot, refined, weights)

    @torch.no_grad()
    def set_expression_range(self, expression: Tensor) -> None:
        """Scale the expression colours to the training frames' ``expression [F, E]`` (each
        revealing action's largest coefficient there; ``avatar/expression_colours.py``)."""
        if self.config.expression_colours:
            self.expression_range.copy_(expression_range(expression, self.expression_actions))

    def colours(self, params: BodyParams) -> Tensor:
        """[N, B, 3] the SH coefficients (B bases) under one frame's (batch-1) expression."""
        g = self.gaussians
        if not self.config.expression_colours:
            return g.sh()
        coefficients = params.expression[0, self.expression_actions]
        if not bool((coefficients != 0).any()):
            return g.sh()
        reach = self.expression_reach[g.vertex_ids]  # [N, K]
        offsets = g.splats["sh0_expression"]
        sh0 = expression_sh0(g.splats["sh0"], offsets, coefficients, reach, self.expression_range)
        return torch.cat([sh0, g.splats["shN"]], dim=1)

    # -- rendering ---------------------------------------------------------------------------
    def forward(
        self,
        params: BodyParams,
        camera: Camera,
        background: Tensor | None = None,
        sh_degree: int | None = None,
        raster: RasterConfig | None = None,
    ) -> RenderOutput:
        """Render one frame, differentiably: image [H, W, 3], alpha, depth, means2d, radii.

        background: [3] colour, None for black; sh_degree: SH degree to evaluate (default the
        active one, raised during training).
        """
        return self.rasterize_posed(self.pose(params), camera, background, sh_degree, raster)

    def rasterize_posed(
        self,
        posed: PosedGaussians,
        camera: Camera,
        background: Tensor | None = None,
        sh_degree: int | None = None,
        raster: RasterConfig | None = None,
    ) -> RenderOutput:
        """Rasterize already posed Gaussians (``forward`` = ``pose`` + this)."""
        camera = camera.to(posed.means.device, posed.means.dtype)
        degree = self.active_sh_degree if sh_degree is None else min(sh_degree, self.gaussians.sh_degree)
        dirs = posed.means - camera.center  # world view directions, into canonical space:
        # R^T d as a sum over R's rows: N batched 3x3 matmuls are slow on CPU.
        dirs = (posed.rotations * dirs.unsqueeze(-1)).sum(dim=-2)
        colors = eval_sh(degree, posed.sh, dirs)
        if background is not None:
            background = background.to(colors)
        return rasterize(
            posed.means,
            posed.quats,
            posed.scales,
            posed.opacities,
            colors,
            camera.viewmat,
            camera.K,
            camera.width,
            camera.height,
            background=background,
            config=raster,
            eps2d=self.config.eps2d,
            rasterize_mode=self.config.rasterize_mode,
        )

    @torch.no_grad()
    def render(self, params: BodyParams, camera: Camera, background: Tensor | None = None) -> Tensor:
        """The service's call: image [H, W, 3] in [0, 1] for one pose (batch-1 ``params``)."""
        if background is None:
            background = torch.ones(3)
        return self(params, camera, background).image.clamp(0.0, 1.0)


def template_vertices(body: BodyModel, shape: Tensor, expression: Tensor | None = None) -> Tensor:
    """[V, 3] rest vertices of ``body`` with ``shape [S]`` and ``expression [E]`` (None: zero)."""
    params = body.default_params(1)
    params.shape = shape.to(params.shape).reshape(1, -1)
    if expression is not None:
        params.expression = expression.to(params.expression).reshape(1, -1)
    with torch.no_grad():
        return body.canonical(params)[0]
