"""Training configuration: dataclasses with the paper's defaults, and the named presets.

EVA (§4.1, appendix): 2,000 iterations, densification between iterations 400 and 1,000 (every
100 as in 3DGS), loss weights lambda_m = 0.1, lambda_s = 0.01, lambda_l = 0.04, everything else as
3DGS (learning rates below). One departure, measured: lambda_s = 0.2, 3DGS's (``train/losses.py``).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

from eva_engine.avatar.config import AvatarConfig
from eva_engine.recipes import PRESETS
from eva_engine.train.face_views import FaceViewConfig
from eva_engine.train.frame_order import ExpressionEventsConfig
from eva_engine.train.losses import LossConfig
from eva_engine.train.pose_correction import PoseCorrectionConfig
from eva_engine.train.regularizers import RegularizerConfig
from eva_engine.train.strategy import DefaultStrategy, Strategy


@dataclass(frozen=True)
class OptimConfig:
    """Adam learning rates (3DGS's, with lengths in metres: a person is a ~1 m scene).

    The means' rate decays exponentially from ``means_lr`` to ``means_lr_final`` over the run, or
    over ``means_lr_steps`` steps when set (3DGS and the official EVA code: 30,000, so a
    2,000-step run ends at 1.18e-4). ``mlp_lr`` is for the weight-offset and pose-refinement
    MLPs unless ``weight_offsets_lr`` / ``pose_refine_lr`` set their own (the official code: 5e-5
    and 5e-6, the latter times ``pose_refine_part_scale`` per part, 0.05 for hands and face);
    ``loss_lr`` is for learnable parts of the loss (e.g. a confidence network).
    ``sh0_expression_lr`` is for the colour offsets per expression action
    (``AvatarConfig.expression_colours``): eight times the base colours' rate, since a blink is
    in a few frames of a clip and its offsets learn from those steps only.
    """

    means_lr: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    opacities_lr: float = 5e-2
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20
    sh0_expression_lr: float = 0.02
    mlp_lr: float = 1e-4
    loss_lr: float = 1e-3
    spatial_scale: float = 1.0
    means_lr_steps: int | None = None
    weight_offsets_lr: float | None = None
    pose_refine_lr: float | None = None
    pose_refine_part_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        if self.means_lr_steps is not None and self.means_lr_steps < 1:
            raise ValueError(f"means_lr_steps must be >= 1 or None, got {self.means_lr_steps}")
        if len(self.pose_refine_part_scale) != 3:
            raise ValueError(f"pose_refine_part_scale needs 3 values, got {self.pose_refine_part_scale}")

    def faster(self, factor: float) -> OptimConfig:
        """Rates for a schedule ``factor`` times shorter than the paper's: colours x factor,
        geometry (means, scales) x min(factor, 3) (larger steps there shred the surface)."""
        geo = min(factor, 3.0)
        return dataclasses.replace(
            self,
            means_lr=self.means_lr * geo,
            means_lr_final=self.means_lr_final * geo,
            scales_lr=self.scales_lr * geo,
            sh0_lr=self.sh0_lr * factor,
            shN_lr=self.shN_lr * factor,
            sh0_expression_lr=self.sh0_expression_lr * factor,
        )

    def splat_lrs(self) -> dict[str, float]:
        return {
            "means": self.means_lr * self.spatial_scale,
            "scales": self.scales_lr,
            "quats": self.quats_lr,
            "opacities": self.opacities_lr,
            "sh0": self.sh0_lr,
            "shN": self.shN_lr,
            "sh0_expression": self.sh0_expression_lr,
        }


@dataclass
class TrainConfig:
    """Everything one training run needs besides the data.

    iterations: optimisation steps, one training frame each (EVA: 2,000).
    regularizers: weights of the avatar's own regularisers (GART's, 0 by default; the
        thin-along-the-normal term, on: ``train/regularizers.py``).
    sh_degree_interval: raise the active SH degree every this many steps (3DGS: 1,000).
    background: render/target background [3]; None: the dataset's (meta.background) or white.
    random_background: each step renders on, and composites its target over, a random colour
        instead (the person mask decides the target's pixels): a Gaussian can no longer hide
        against the background's colour, so the alpha must be right everywhere.
    pose_noise: standard deviation (radians) of a noise added to every body joint's rotation
        (not the fingers' or the face's) of a step's frame, drawn anew each step: the avatar
        learns its shape near each pose, not only at it.
    image_scale: resample frames (and intrinsics) by this factor before training.
    face_view: the dataset's face close-ups as a second view of their frames (``train/face_views.py``).
    expression_events: the frames of a rare expression (a blink) visited more often
        (``train/frame_order.py``; off by default).
    seed: the initial weights, the seed vertices and the frame order (the density-control strategy
    has its own ``seed``). Runs on one CPU thread are bit-identical given it; with more threads,
    oneDNN's convolution backward may sum in another order and the last bits differ.
    device: "cpu" or "cuda" (an error if CUDA is asked for and absent). Torch's CPU threads are the
    process's: its entry point sets them (``torch.set_num_threads``), not a training run.
    """

    iterations: int = 2000
    avatar: AvatarConfig = field(default_factory=AvatarConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    strategy: Strategy = field(default_factory=DefaultStrategy)
    pose_correction: PoseCorrectionConfig = field(default_factory=PoseCorrectionConfig)
    regularizers: RegularizerConfig = field(default_factory=RegularizerConfig)
    sh_degree_interval: int = 1000
    background: tuple[float, float, float] | None = None
    random_background: bool = False
    pose_noise: float = 0.0
    image_scale: float = 1.0
    face_view: FaceViewConfig = field(default_factory=FaceViewConfig)
    expression_events: ExpressionEventsConfig = field(default_factory=ExpressionEventsConfig)
    seed: int = 0
    device: str = "cpu"
    progress_every: int = 10

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if not 0.0 < self.image_scale <= 4.0:
            raise ValueError(f"image_scale must be in (0, 4], got {self.image_scale}")
        if not 0.0 <= self.pose_noise <= 1.0:
            raise ValueError(f"pose_noise must be in [0, 1] radians, got {self.pose_noise}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["strategy"] = {"name": type(self.strategy).__name__, **dataclasses.asdict(self.strategy)}
        return d


def preset(name: str, **overrides) -> TrainConfig:
    """The configuration of a preset of ``eva_engine.recipes.PRESETS`` (the table holds each
    preset's schedule and model size: ``default`` the paper's, ``fast`` 600 iterations with
    faster rates and smaller MLPs, ``tiny`` seconds for tests); ``overrides`` replace top-level
    ``TrainConfig`` fields.

    Every preset carries the Gaussians an expression moves by the skin's frame
    (``AvatarConfig.expression_frames``: closed lids cover the eye; ``docs/alignment.md``).

    Per-frame pose correction is off in every preset (its schedule is set, ``enabled=False``):
    test frames are rendered with uncorrected poses, and an avatar trained on corrected ones
    scores worse on them (``bench/results/time_to_quality_pose_correction.md`` against
    ``time_to_quality.md``; on real video with ``zero_mean`` too: ``real_videos_zm.md``).
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {list(PRESETS)}")
    p = PRESETS[name]
    correction = {"start_iter": p.pose_correction_start, "lr": p.pose_correction_lr}
    schedule = {"iterations": p.iterations, "sh_degree_interval": p.sh_degree_interval}
    cfg = TrainConfig(
        avatar=AvatarConfig(**p.avatar),
        optim=OptimConfig().faster(p.rate_speedup) if p.rate_speedup else OptimConfig(),
        strategy=(
            DefaultStrategy(
                refine_start_iter=p.refine[0], refine_stop_iter=p.refine[1], refine_every=p.refine[2]
            )
            if p.refine
            else DefaultStrategy()
        ),
        pose_correction=PoseCorrectionConfig(
            enabled=False, **{k: v for k, v in correction.items() if v is not None}
        ),
        **{k: v for k, v in {**schedule, "progress_every": p.progress_every}.items() if v is not None},
    )
    return dataclasses.replace(cfg, **overrides) if overrides else cfg


def with_overrides(config: TrainConfig, assignments: list[str]) -> TrainConfig:
    """``config`` with dotted fields set, e.g. ``["loss.lpips_every=2",
    "avatar.detach_weight_inputs=true"]`` (values read as JSON, else as a string): how a benchmark
    compares one setting against another without a new preset or method."""
    for assignment in assignments:
        path, sep, text = assignment.partition("=")
        if not sep or not path:
            raise ValueError(f"expected field.path=value, got {assignment!r}")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        config = _replace_path(config, path.split("."), value, path)
    return config


def _replace_path(obj, names: list[str], value, path: str):
    name = names[0]
    if not dataclasses.is_dataclass(obj) or name not in {f.name for f in dataclasses.fields(obj)}:
        raise ValueError(f"{path!r}: {type(obj).__name__} has no field {name!r}")
    if len(names) > 1:
        value = _replace_path(getattr(obj, name), names[1:], value, path)
    elif isinstance(value, list):
        value = tuple(value)
    return dataclasses.replace(obj, **{name: value})
