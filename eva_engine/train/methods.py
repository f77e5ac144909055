"""The paper's methods and ablations (``eva_engine.recipes.METHODS``) as switches on one
``TrainConfig`` (no copies):

- ``3dgs+body``: the Table-1 baseline, 3DGS on the articulated body: ``DefaultStrategy``
  (constant threshold, template-distance pruning) and 3DGS's own objective, 0.8 L1 + 0.2 D-SSIM
  (D-SSIM on the same person crop as EVA's SSIM term), plus the mask term; no LPIPS term (3DGS
  does not train on LPIPS). Everything else is EVA's: schedule, learning rates, initialisation,
  LBS weight offsets, pose refiner, pixel normalisation.
- ``gauhuman+body``: GauHuman (Hu et al., CVPR 2024) on the articulated body: its KL-guided
  clone, split and merge (``KLStrategy``) and its objective, L1 + 0.1 mask + 0.01 (1 - SSIM) +
  0.01 LPIPS on the person crop. GauHuman's LPIPS term uses VGG; ours uses AlexNet like every
  method here, so that LPIPS-VGG stays a metric no method trained on. Its pose refiner and LBS
  weight offsets are the ones EVA took from it (the same modules, on by default); schedule,
  learning rates and initialisation on the template are shared with the other rows.
- ``gart+body``: GART (Lei et al., CVPR 2024) on the articulated body: its learnable skinning
  field (a voxel grid of LBS weights, initialised from the body model's) and 4 latent bones
  driven by the pose (``avatar/skinning_field.py``) in place of the weight-offset MLP and the pose
  refiner; 3DGS's density control with GART's thresholds and opacity-only pruning; its objective,
  L1 + 0.1 D-SSIM (no mask or LPIPS term) plus its regularisers (``regularizers.py``); its
  initial opacity 0.99. Schedule and learning rates are the preset's (``docs/baselines.md``).
- ``eva``: context-aware density control (``ContextAwareStrategy``, per-Gaussian history) and the
  confidence-aware loss, with the full objective (mask, SSIM, LPIPS; paper eq. 11), its
  SSIM weight 3DGS's 0.2 rather than the paper's 0.01 (``train/losses.py``).
- ``eva-no-cadc`` / ``eva-no-cl``: Table 2's ablations (``DefaultStrategy`` / plain L1).
- ``eva-no-cadc-no-cl``: both contributions off (the full objective alone): what separates the
  baseline's objective from EVA's.
- ``eva-part-mean``: EVA with the official code's per-part-mean thresholds.
- ``eva-official``: EVA as the authors' code (kolassa-tema/EVA_Official) runs it: its
  densification (``ContextAwareStrategy(history="official")``: part means with clones as zeros,
  no history at the first event, λ on splits only, no floor; events one interval later, as its
  ``iteration > densify_from_iter``), its confidence form (``confidence_official``), its loss
  weights (SSIM 0.01) with LPIPS-**VGG** as the loss network (trained on the metric: the tables
  mark it), and its constants (``OFFICIAL``): learning rates, initial opacity 0.004, every
  template vertex as a seed, a black background, SH degree +1 every 1,000 steps.
  ``eva-official-no-cadc``: the same with 3DGS's density control.

None of them has the product's thin-along-the-normal regulariser (``PAPER_REGULARIZERS``), the
novel-pose fix of ``docs/novel-views.md``, its Gaussians carried by the skin's frame under an
expression (``AvatarConfig.expression_frames``) or its colours that follow the expression
(``AvatarConfig.expression_colours``, both ``docs/alignment.md``): the paper's rows stay the
published methods.
All of them keep ``DefaultStrategy.prune_unseen_parts`` (a part no training frame shows gets no
Gaussians): on data that shows every part it changes nothing, so the paper's rows are unaffected.

    cfg = with_method(preset("fast"), "eva")
"""

from __future__ import annotations

import dataclasses

from eva_engine.avatar.config import AvatarConfig
from eva_engine.recipes import METHODS
from eva_engine.train.config import OptimConfig, TrainConfig
from eva_engine.train.regularizers import RegularizerConfig
from eva_engine.train.strategy import ContextAwareStrategy, DefaultStrategy, KLStrategy

# GART's PeopleSnapshot profile (profiles/people/people_1m.yaml): its densification thresholds
# (MAX_GRAD, PERCENT_DENSE x its extent 0.5), opacity-only pruning (1 m: no size or template
# limit), its initial opacity and its regularisers.
GART_STRATEGY = {
    "grow_grad2d": 1e-4,
    "grow_scale3d": 0.005,
    "prune_opa": 0.1,
    "prune_scale3d": 1.0,
    "prune_template_dist": 1.0,
}
PAPER_REGULARIZERS = RegularizerConfig(lambda_thin=0.0)
"""None: the product's thin-along-the-normal term (``regularizers.py``) is not in any paper's
method, so their rows stay the published methods."""
GART_REGULARIZERS = RegularizerConfig(
    lambda_thin=0.0,
    knn=3,
    lambda_knn_std=1e-3,
    lambda_field_tv=0.3,
    lambda_latent_tv=0.5,
    lambda_field_norm=0.3,
    lambda_latent_norm=0.3,
    lambda_small_scale=0.05,
)
GART_LATENT_BONES = 4


@dataclasses.dataclass(frozen=True)
class OfficialRecipe:
    """The official EVA code's constants (``arguments/__init__.py``, ``scene/gaussian_model.py``,
    ``train.py``), what ``recipe="official"`` methods set on a preset. Its splat rates (features
    2.5e-3, opacity 0.05, scaling 5e-3, rotation 1e-3) are ``OptimConfig``'s defaults.

    The pose refiner's rate is constant here; the official one starts 200 steps at 1% and decays
    from 5e-6 towards 1e-7 over 30,000 steps (3.9e-6 at step 2,000).
    """

    optim: OptimConfig = OptimConfig(
        means_lr=1.6e-4,
        means_lr_final=1.6e-6,
        means_lr_steps=30_000,
        weight_offsets_lr=5e-5,
        pose_refine_lr=5e-6,
        pose_refine_part_scale=(1.0, 0.05, 0.05),
        loss_lr=1e-3,
    )
    init_opacity: float = 0.004
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sh_degree_interval: int = 1000
    lambda_ssim: float = 0.01
    lpips_net: str = "vgg"


OFFICIAL = OfficialRecipe()


def with_method(config: TrainConfig, method: str) -> TrainConfig:
    """``config`` (its schedule, seeds, learning rates, model sizes) switched to ``method``
    (module docstring): the method sets the density control and its thresholds, the objective,
    the skinning and the regularisers. The config's strategy must be a ``DefaultStrategy`` (its
    schedule is kept)."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {list(METHODS)}")
    switches = METHODS[method]
    base = config.strategy
    if not isinstance(base, DefaultStrategy):
        raise TypeError(f"with_method needs a DefaultStrategy-based config, got {type(base).__name__}")
    # Back to the baseline: its schedule fields, the method's thresholds.
    thresholds = (
        GART_STRATEGY
        if switches.density == "gart"
        else {k: getattr(DefaultStrategy, k) for k in GART_STRATEGY}
    )
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(DefaultStrategy)}
    base = DefaultStrategy(**{**fields, **thresholds})
    strategy = base
    if switches.density == "cadc":
        strategy = ContextAwareStrategy.from_default(base, history=switches.history)
    elif switches.density == "kl":
        strategy = KLStrategy.from_default(base)
    loss = dataclasses.replace(config.loss, photometric="confidence" if switches.confidence else "l1")
    if switches.objective == "3dgs":
        loss = dataclasses.replace(loss, lambda_photometric=0.8, lambda_ssim=0.2, lambda_lpips=0.0)
    elif switches.objective == "gauhuman":
        loss = dataclasses.replace(loss, lambda_ssim=0.01, lambda_lpips=0.01)
    elif switches.objective == "gart":
        loss = dataclasses.replace(loss, lambda_ssim=0.1, lambda_lpips=0.0, lambda_mask=0.0)
    field = switches.skinning == "field"
    avatar = dataclasses.replace(
        config.avatar,
        skinning=switches.skinning,
        weight_offsets=not field,
        pose_refine=not field,
        latent_bones=GART_LATENT_BONES if field else 0,
        init_opacity=0.99 if field else AvatarConfig.init_opacity,
        expression_frames=False,
        expression_colours=False,
        rasterize_mode="classic",
        eps2d=AvatarConfig.eps2d,  # 3DGS's rasterizer, as the paper's
    )
    regularizers = GART_REGULARIZERS if switches.objective == "gart" else PAPER_REGULARIZERS
    config = dataclasses.replace(
        config, strategy=strategy, loss=loss, avatar=avatar, regularizers=regularizers
    )
    return with_official_recipe(config, switches.density) if switches.recipe == "official" else config


def with_official_recipe(config: TrainConfig, density: str) -> TrainConfig:
    """``config`` (a method's, on a preset) with the official code's densification, confidence
    form, loss and constants (module docstring, ``OfficialRecipe``); its schedule (iterations,
    densification window) stays the preset's."""
    r = OFFICIAL
    strategy = config.strategy
    # The official events come at iteration > densify_from_iter (1-based): one interval later.
    strategy = dataclasses.replace(
        strategy, refine_start_iter=strategy.refine_start_iter + strategy.refine_every
    )
    if density == "cadc":
        strategy = dataclasses.replace(strategy, history="official", min_threshold_ratio=0.0)
    photometric = (
        "confidence_official" if config.loss.photometric == "confidence" else config.loss.photometric
    )
    loss = dataclasses.replace(
        config.loss, photometric=photometric, lambda_ssim=r.lambda_ssim, lpips_net=r.lpips_net
    )
    avatar = dataclasses.replace(config.avatar, init_opacity=r.init_opacity, init_max_gaussians=None)
    optim = dataclasses.replace(r.optim, spatial_scale=config.optim.spatial_scale)
    return dataclasses.replace(
        config,
        strategy=strategy,
        loss=loss,
        avatar=avatar,
        optim=optim,
        background=r.background,
        sh_degree_interval=r.sh_degree_interval,
    )
