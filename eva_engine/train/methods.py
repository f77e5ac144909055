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

None of them has the product's thin-along-the-normal regulariser (``PAPER_REGULARIZERS``), the
novel-pose fix of ``docs/novel-views.md``: the paper's rows stay the published methods.
All of them keep ``DefaultStrategy.prune_unseen_parts`` (a part no training frame shows gets no
Gaussians): on data that shows every part it changes nothing, so the paper's rows are unaffected.

    cfg = with_method(preset("fast"), "eva")
"""

from __future__ import annotations

import dataclasses

from eva_engine.avatar.config import AvatarConfig
from eva_engine.recipes import METHODS
from eva_engine.train.config import TrainConfig
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
    )
    regularizers = GART_REGULARIZERS if switches.objective == "gart" else PAPER_REGULARIZERS
    return dataclasses.replace(config, strategy=strategy, loss=loss, avatar=avatar, regularizers=regularizers)
