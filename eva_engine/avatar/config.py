"""``AvatarConfig``: what the avatar model is (not how it is trained)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from eva_engine.render.rasterize import RASTERIZE_MODES

# The expression actions that cover or uncover something: the lids, the jaw (Anny's ARKit names).
REVEALING_ACTIONS = ("eyeBlinkLeft", "eyeBlinkRight", "jawOpen")
# The default's share of them: the blinks. The jaw's offsets fit a take's few open-jaw frames
# and made the face worse in new poses (docs/alignment.md, "Colours that follow the expression").
BLINK_ACTIONS = ("eyeBlinkLeft", "eyeBlinkRight")

SKINNING_KINDS = ("mesh", "field")
TEMPLATE_EXPRESSIONS = ("neutral", "median")


@dataclass(frozen=True)
class AvatarConfig:
    """Architecture of a Gaussian avatar (EVA §3.1).

    sh_degree: highest spherical-harmonics degree stored (training starts at 0 and raises it).
    init_opacity: opacity of the initial Gaussians (3DGS: 0.1).
    init_max_gaussians: seed at most this many surface vertices (a seeded random subset), None
        for one Gaussian per surface vertex of the body model.
    weight_offsets: learn LBS-weight offsets w' (off: plain nearest-vertex skinning weights).
    pose_refine: learn the pose-refinement MLPs (off: the input pose as given).
    pe_frequencies: positional-encoding octaves of the canonical centres for the weight MLP.
    mlp_width, mlp_depth: hidden width and hidden-layer count of both MLPs.
    mlp_out_init: half-range of the uniform init of both MLPs' last layers (bias 0), so they
        start as (almost exactly) the identity: EVA's official code uses 1e-5.
    lbs_eps: epsilon in w = softmax(log(w_body + eps) + w') (paper: 1e-8).
    detach_weight_inputs: the weight-offset MLP reads the centres detached, as EVA's and
        GauHuman's official code do (``f_w(p.detach())``): the skinning weights' gradient then
        trains the MLP only, not the centres (and the backward skips the encoding).
    skinning: "mesh" (EVA, GauHuman: the nearest template vertex's weights, with the weight-offset
        MLP if ``weight_offsets``) or "field" (GART: a learnable voxel field of weights,
        ``avatar/skinning_field.py``; ``weight_offsets`` must then be off).
    field_resolution: the field's grid side in x and y (GART: 64; z has a quarter of it).
    latent_bones: GART's extra bones driven by the pose (field skinning only; GART: 4).
    max_scale: the largest standard deviation a Gaussian may have, per part (body, hand, face),
        in metres; training projects the scales back under it after every step (None: unbounded,
        as 3DGS). A Gaussian stretched along the training camera's rays costs nothing in the
        training images and becomes a spike from any other view (``docs/novel-views.md``).
    init_normal_ratio: the initial Gaussians' extent along the body surface's normal, as a
        fraction of their extent along it (1: isotropic, as 3DGS).
    expression_frames: an expression also turns and scales each Gaussian with the skin around
        its vertex (a closing lid stretches and faces the camera; ``avatar/surface_frames.py``);
        off: the vertex's offset only, as avatars saved before it have.
    expression_colours: every Gaussian also carries a colour offset per revealing expression
        action, blended by the frame's coefficients where the action moves its vertex (a closing
        lid turns skin-coloured, an open mouth dark; ``avatar/expression_colours.py``).
    expression_colour_actions: those actions by name, the body model's that it has (None: all
        its actions; a model with none of the names, such as SMPL-X: none). The blinks by
        default; ``REVEALING_ACTIONS`` adds the jaw.
    expression_colour_spread: metres: an action also recolours the Gaussians whose vertex lies
        within this distance of a vertex it moves (at rest), such as the eyeball behind a closing
        lid, which the blink covers but does not move, and no longer what it moves far away
        (``expression_colours.action_reach``); 0: everything it moves, nothing else.
    template_expression: the face the canonical Gaussians sit on. ``"neutral"``: the body model's
        zero expression. ``"median"``: the training frames' median expression, the face the video
        shows most of the time (a talking person's jaw a little open, wide eyes' lids raised), so
        new Gaussians start, and attach to vertices, where that face has its lips and lids. A
        frame poses them where the neutral template would (``docs/alignment.md``, "Gaussians seen
        through the eye's opening").
    eye_binding: Gaussians seen through an eye's opening on the template attach to the eyeball
        whenever the Gaussians are attached again (``avatar/eye_binding.py``), so the painted iris
        stays on the eyeball when a blink's lid comes down instead of sliding down with it; a body
        model without eye pieces has none to attach to.
    weight_mlp_bf16: while training, the weight-offset MLP multiplies in bfloat16 (its output,
        softmax and parameter gradients stay float32; ``networks.relu_mlp``). Rendering a trained
        avatar is float32 either way. Worth it where the CPU has native bfloat16 (AVX512-BF16).
    rasterize_mode: ``render.rasterize``'s mode, in training and in every render after it.
        "classic" (3DGS): a Gaussian narrower than a pixel is widened to eps2d at full opacity.
        "antialiased" (gsplat's mode, Mip-Splatting's 2D filter): its opacity falls as it widens,
        so a face trained on close-ups at three times the frame's pixels is not drawn thicker and
        darker in the frame (``docs/novel-views.md``, "The face close-ups from new views").
    eps2d: pixels^2 added to every 2D covariance (3DGS: 0.3, this default, what avatars saved
        without it were trained with; Mip-Splatting's 2D filter: 0.1, about the variance of a
        one-pixel box filter, which every preset sets: ``docs/novel-views.md``).
    """

    sh_degree: int = 3
    init_opacity: float = 0.1
    init_max_gaussians: int | None = None
    weight_offsets: bool = True
    pose_refine: bool = True
    pe_frequencies: int = 6
    mlp_width: int = 128
    mlp_depth: int = 2
    mlp_out_init: float = 1e-5
    lbs_eps: float = 1e-8
    detach_weight_inputs: bool = False
    skinning: str = "mesh"
    field_resolution: int = 64
    latent_bones: int = 0
    max_scale: tuple[float, float, float] | None = None
    init_normal_ratio: float = 1.0
    expression_frames: bool = False
    expression_colours: bool = False
    expression_colour_actions: tuple[str, ...] | None = BLINK_ACTIONS
    expression_colour_spread: float = 0.0
    template_expression: str = "neutral"
    eye_binding: bool = False
    weight_mlp_bf16: bool = False
    rasterize_mode: str = "classic"
    eps2d: float = 0.3

    def __post_init__(self) -> None:
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if self.init_max_gaussians is not None and self.init_max_gaussians < 1:
            raise ValueError("init_max_gaussians must be positive or None")
        if self.mlp_depth < 1 or self.mlp_width < 1 or self.pe_frequencies < 0:
            raise ValueError("mlp_depth, mlp_width must be >= 1 and pe_frequencies >= 0")
        if self.skinning not in SKINNING_KINDS:
            raise ValueError(f"skinning must be one of {SKINNING_KINDS}, got {self.skinning!r}")
        if self.skinning == "field" and self.weight_offsets:
            raise ValueError("field skinning learns its own weights: turn weight_offsets off")
        if self.latent_bones < 0 or (self.latent_bones and self.skinning != "field"):
            raise ValueError("latent_bones must be >= 0, and > 0 only with field skinning")
        if self.max_scale is not None and (len(self.max_scale) != 3 or min(self.max_scale) <= 0):
            raise ValueError("max_scale must be three positive lengths (body, hand, face) or None")
        if not 0.0 <= self.expression_colour_spread < 0.05:
            raise ValueError(
                f"expression_colour_spread must be in [0, 0.05) m, got {self.expression_colour_spread}"
            )
        if self.template_expression not in TEMPLATE_EXPRESSIONS:
            raise ValueError(
                f"template_expression must be one of {TEMPLATE_EXPRESSIONS}, got {self.template_expression!r}"
            )
        if not 0.0 < self.eps2d <= 1.0:
            raise ValueError(f"eps2d must be in (0, 1] px^2, got {self.eps2d}")
        if self.rasterize_mode not in RASTERIZE_MODES:
            raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {self.rasterize_mode!r}")
        if not 0.0 < self.init_normal_ratio <= 1.0:
            raise ValueError(f"init_normal_ratio must be in (0, 1], got {self.init_normal_ratio}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> AvatarConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown AvatarConfig field(s) {sorted(unknown)}")
        for key in ("max_scale", "expression_colour_actions"):  # lists in JSON
            if data.get(key) is not None:
                data = {**data, key: tuple(data[key])}
        return cls(**data)
