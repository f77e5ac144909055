"""Training recipes by name, the one list of each: the presets (schedule and model size) and the
methods (the paper's, its baseline, its ablations). ``eva_engine.train`` builds them (``preset``,
``with_method``); ``eva train``, ``eva demo``, the job options of the service and its web page
offer exactly these.

Plain data: reading it imports no torch, so the job queue's processes and ``eva --help`` start
without it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class Preset:
    """A training schedule and model size (``eva_engine.train.preset`` builds its ``TrainConfig``;
    a field left None keeps ``TrainConfig``'s default, the paper's).

    summary: what it is for. iterations: optimisation steps. rate_speedup: learning rates for a
    schedule this many times shorter than the paper's (``OptimConfig.faster``). refine: the
    density control's first step, last step and interval. sh_degree_interval: steps between SH
    degree raises. progress_every: steps between progress reports. pose_correction_start /
    pose_correction_lr: the per-frame pose correction's schedule (off in every preset: its
    ``enabled`` stays False). avatar: ``AvatarConfig`` fields.
    """

    summary: str
    iterations: int | None = None
    rate_speedup: float | None = None
    refine: tuple[int, int, int] | None = None
    sh_degree_interval: int | None = None
    progress_every: int | None = None
    pose_correction_start: int | None = None
    pose_correction_lr: float | None = None
    avatar: dict[str, int | float | bool] = field(default_factory=dict)


EVERY_PRESET_AVATAR: dict[str, int | float | bool] = {
    "expression_frames": True,
    "expression_colours": True,
    "expression_colour_spread": 0.006,
    "eps2d": 0.1,
}
"""The ``AvatarConfig`` fields every preset sets: the Gaussians an expression moves by the skin's
frame, the lids recoloured with the blinks, and the eyeball the lids cover (closed lids cover the
eye: docs/alignment.md); a 0.1 px² dilation, not 3DGS's 0.3 (sharper in new poses:
docs/novel-views.md, "The rasterizer's 2D dilation")."""

PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        "seconds, a test",
        iterations=100,
        rate_speedup=10.0,
        refine=(30, 70, 20),
        sh_degree_interval=50,
        progress_every=5,
        avatar={
            "sh_degree": 1,
            "init_max_gaussians": 1500,
            "mlp_width": 32,
            "pe_frequencies": 4,
            "field_resolution": 32,
            **EVERY_PRESET_AVATAR,
        },
    ),
    "fast": Preset(
        "minutes",
        iterations=600,
        rate_speedup=2000 / 600,
        refine=(120, 300, 30),
        sh_degree_interval=300,
        pose_correction_start=120,
        pose_correction_lr=4e-3,
        avatar={
            "init_max_gaussians": 6000,
            "mlp_width": 64,
            **EVERY_PRESET_AVATAR,
        },
    ),
    "default": Preset(
        "the paper's",
        pose_correction_start=400,
        # The MLPs 64 wide, not 128: 15% less training time, quality no worse (docs/speed.md).
        avatar={
            "mlp_width": 64,
            **EVERY_PRESET_AVATAR,
        },
    ),
}
"""Preset name -> its schedule and model size: the one table of them."""


@dataclass(frozen=True)
class Method:
    """What a method switches on a preset's config (``eva_engine.train.with_method``).

    density: ``3dgs`` (3DGS's ``DefaultStrategy``), ``cadc`` (EVA's context-aware density
    control, §3.3), ``kl`` (GauHuman's KL-guided clone, split and merge) or ``gart`` (3DGS's with
    GART's thresholds, opacity pruning only). history: CADC's thresholds, ``per_gaussian`` (the
    paper's) or ``part_mean`` (the official code's). confidence: the confidence-aware loss (§3.4;
    else plain L1). objective: ``full`` (mask, SSIM and LPIPS terms, eq. 11, SSIM at 3DGS's weight
    0.2), ``gauhuman`` (the same terms with GauHuman's SSIM and LPIPS weights, 0.01), ``gart``
    (L1 + 0.1 D-SSIM, and GART's regularisers) or ``3dgs`` (3DGS's 0.8 L1 + 0.2 D-SSIM, and the
    mask term; no LPIPS).
    skinning: ``mesh`` (the template's weights with the weight-offset MLP, and the pose refiner)
    or ``field`` (GART's learnable weight field and latent bones, no pose refiner).
    recipe: ``project`` (the preset's schedule and rates, the project's forms of CADC and CL) or
    ``official`` (the official EVA code's: its densification, its confidence form, LPIPS-VGG as
    the loss network, its constants: ``eva_engine.train.methods.OFFICIAL``).
    """

    summary: str
    density: Literal["3dgs", "cadc", "kl", "gart"]
    confidence: bool
    history: Literal["per_gaussian", "part_mean"] = "per_gaussian"
    objective: Literal["full", "gauhuman", "gart", "3dgs"] = "full"
    skinning: Literal["mesh", "field"] = "mesh"
    recipe: Literal["project", "official"] = "project"


METHODS: dict[str, Method] = {
    "3dgs+body": Method("baseline", density="3dgs", confidence=False, objective="3dgs"),
    "gart+body": Method(
        "GART's baseline", density="gart", confidence=False, objective="gart", skinning="field"
    ),
    "gauhuman+body": Method("GauHuman's baseline", density="kl", confidence=False, objective="gauhuman"),
    "eva": Method("the paper's", density="cadc", confidence=True),
    "eva-no-cadc": Method("eva without CADC", density="3dgs", confidence=True),
    "eva-no-cl": Method("eva without CL", density="cadc", confidence=False),
    "eva-no-cadc-no-cl": Method("eva without CADC and CL", density="3dgs", confidence=False),
    "eva-part-mean": Method(
        "eva, per-part-mean thresholds", density="cadc", confidence=True, history="part_mean"
    ),
    "eva-official": Method(
        "eva as the authors' code has it", density="cadc", confidence=True, recipe="official"
    ),
    "eva-official-no-cadc": Method(
        "eva-official without CADC", density="3dgs", confidence=True, recipe="official"
    ),
}
"""Method name -> its switches (Tables 1 and 2 of the paper: ``eva_engine.train.methods``)."""


def describe_presets() -> str:
    """The presets in words, for help texts: ``tiny (seconds, a test), fast (minutes), ...``."""
    return ", ".join(f"{name} ({p.summary})" for name, p in PRESETS.items())


def describe_methods() -> str:
    """The methods in words, for help texts: ``3dgs+body (baseline), eva (the paper's), ...``."""
    return ", ".join(f"{name} ({method.summary})" for name, method in METHODS.items())
