"""Per-frame pose correction: learnable residuals on each training frame's fitted pose.

A fit from monocular video is never exact, and every frame is off in its own way; an avatar
trained on those poses averages slightly different placements of the same surface (ghosted arm
edges, smeared fingers). Each training frame t gets its own residuals, starting at zero:

    root_t' = root_t ∘ δroot_t,   joint_t,j' = joint_t,j ∘ δ_t,j   (rotation composition)
    transl_t' = transl_t + δtransl_t,   expression_t' = expression_t + δexpr_t

optimised with the avatar, and held to the fit by a quadratic prior per group (``weights``):
the image moves a frame's pose only as far as the photometric gain outweighs the prior. The
corrections start after ``start_iter`` (the avatar must first look like the person, or the
residuals would explain its initial errors), and each frame's residuals are separate
parameters, so a step moves only the frame it rendered (Adam skips parameters without
gradients).

With ``zero_mean`` each frame gets its residuals minus their mean over the frames: what every
frame's fit shares (a bias of the fit, which the test frames and a user's poses share too) stays
in the poses the avatar learns from, and only each frame's own deviation is corrected. Without
it the residuals can move every frame alike, and the avatar learns a body placed where no
uncorrected pose puts it. The prior acts on the parameters before the mean is taken, so the
shared part cannot drift without bound. Measured on real video it scores worse than no
correction on hands and faces (``bench/results/real_videos_zm.md``); it is opt-in.

Test frames are not corrected during training: they are rendered with their fitted poses (the
main protocol). ``refine_poses`` runs the same correction with the avatar frozen, which is what
a test-time refinement protocol uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch
from torch import Tensor, nn

from eva_engine.body.model import PART_NAMES
from eva_engine.body.params import BodyParams

GROUPS = ("root", "transl", "body", "hand", "face", "expression")


@dataclass(frozen=True)
class PoseCorrectionConfig:
    """enabled: learn per-frame residuals; lr: their Adam rate (radians / metres / expression
    units per step); start_iter: first training step that moves them; weights: the prior's
    weight per group (rotation groups on squared radians, translation on squared metres,
    expression on squared coefficients), a group absent from ``groups`` is not corrected;
    zero_mean: apply each frame's residuals minus their mean over the frames (module docstring)."""

    enabled: bool = False
    lr: float = 2e-3
    start_iter: int = 200
    groups: tuple[str, ...] = GROUPS
    weights: tuple[tuple[str, float], ...] = (
        ("root", 0.1),
        ("transl", 1.0),
        ("body", 0.1),
        ("hand", 0.03),
        ("face", 0.1),
        ("expression", 0.03),
    )
    zero_mean: bool = False

    def __post_init__(self) -> None:
        unknown = set(self.groups) - set(GROUPS)
        if unknown:
            raise ValueError(f"unknown pose-correction groups {sorted(unknown)}; valid: {GROUPS}")
        if self.lr <= 0 or self.start_iter < 0:
            raise ValueError("lr must be > 0 and start_iter >= 0")

    def weight(self, group: str) -> float:
        return dict(self.weights).get(group, 1.0)


class PoseCorrection(nn.Module):
    """Residuals of T frames (module docstring). ``joint_part_ids [P]``: the part (index into
    ``PART_NAMES``) of each pose joint; ``expression_dim``: E.

    apply(params, t): ``params`` (batch 1, frame t's fit) -> corrected params (batch 1).
    prior(t): the prior's value for frame t (a scalar, differentiable).
    """

    def __init__(
        self, num_frames: int, joint_part_ids: Tensor, expression_dim: int, config: PoseCorrectionConfig
    ) -> None:
        super().__init__()
        self.config = config
        self.register_buffer("joint_part_ids", joint_part_ids.to(torch.int64).clone())
        p = joint_part_ids.numel()
        self.root = nn.ParameterList(nn.Parameter(torch.zeros(3)) for _ in range(num_frames))
        self.transl = nn.ParameterList(nn.Parameter(torch.zeros(3)) for _ in range(num_frames))
        self.joints = nn.ParameterList(nn.Parameter(torch.zeros(p, 3)) for _ in range(num_frames))
        self.expression = nn.ParameterList(
            nn.Parameter(torch.zeros(expression_dim)) for _ in range(num_frames)
        )
        # Joints of parts that are not corrected stay at zero: a mask on their residuals.
        on = torch.tensor([part in config.groups for part in PART_NAMES])
        self.register_buffer("joint_mask", on[self.joint_part_ids].float()[:, None])
        per_joint = torch.tensor([config.weight(part) for part in PART_NAMES])
        self.register_buffer("joint_weight", per_joint[self.joint_part_ids].float())

    @property
    def num_frames(self) -> int:
        return len(self.root)

    def raw(self, t: int) -> dict[str, Tensor]:
        """Frame t's parameters, with the groups that are not corrected at zero."""
        g = self.config.groups
        zero3 = self.root[t].new_zeros(3)
        return {
            "root": self.root[t] if "root" in g else zero3,
            "transl": self.transl[t] if "transl" in g else zero3,
            "joints": self.joints[t] * self.joint_mask,
            "expression": self.expression[t] if "expression" in g else torch.zeros_like(self.expression[t]),
        }

    @torch.no_grad()
    def mean(self) -> dict[str, Tensor]:
        """The residuals' mean over the frames, per group (empty without ``zero_mean``: nothing is
        subtracted)."""
        if not self.config.zero_mean:
            return {}
        stacks = {
            "root": self.root,
            "transl": self.transl,
            "joints": self.joints,
            "expression": self.expression,
        }
        return {k: torch.stack(list(v)).mean(0) for k, v in stacks.items()}

    def delta(self, t: int, mean: dict[str, Tensor] | None = None) -> dict[str, Tensor]:
        """Frame t's applied residuals: ``raw(t)``, minus the mean over the frames with
        ``zero_mean`` (the mean is a constant to the step: its gradient would reach every frame).
        ``mean``: ``self.mean()``, when the caller already has it (one per pass over the frames)."""
        d = self.raw(t)
        for k, m in (self.mean() if mean is None else mean).items():
            d[k] = d[k] - (m * self.joint_mask if k == "joints" else m)
        return d

    def apply(self, params: BodyParams, t: int, mean: dict[str, Tensor] | None = None) -> BodyParams:
        """Frame t's fit (batch 1) with its residuals applied (``mean``: as in ``delta``)."""
        d = self.delta(t, mean)
        dtype = params.joints.dtype
        root = roma.rotvec_composition([params.root_orient, d["root"][None].to(dtype)])
        joints = roma.rotvec_composition([params.joints, d["joints"][None].to(dtype)])
        return BodyParams(
            root_orient=root,
            transl=params.transl + d["transl"][None].to(dtype),
            joints=joints,
            expression=params.expression + d["expression"][None].to(dtype),
            shape=params.shape,
        )

    def prior(self, t: int) -> Tensor:
        """Σ_group weight_group · squared norm of the group's residuals (frame t)."""
        c, d = self.config, self.raw(t)
        total = c.weight("root") * d["root"].square().sum() + c.weight("transl") * d["transl"].square().sum()
        total = total + (self.joint_weight * d["joints"].square().sum(-1)).sum()
        return total + c.weight("expression") * d["expression"].square().sum()

    @torch.no_grad()
    def corrected(self, params: BodyParams) -> BodyParams:
        """All T frames' corrected parameters (``params`` with T rows)."""
        mean = self.mean()
        rows = [self.apply(params[t], t, mean) for t in range(self.num_frames)]
        return BodyParams.cat(rows)

    @torch.no_grad()
    def magnitudes(self) -> dict[str, float]:
        """Mean size of the applied residuals per group over the frames (radians, metres,
        coefficients)."""
        mean = self.mean()
        d = [self.delta(t, mean) for t in range(self.num_frames)]
        out = {
            "root": torch.stack([x["root"] for x in d]).norm(dim=-1).mean(),
            "transl": torch.stack([x["transl"] for x in d]).norm(dim=-1).mean(),
            "expression": torch.stack([x["expression"] for x in d]).abs().mean(),
        }
        joints = torch.stack([x["joints"] for x in d]).norm(dim=-1)  # [T, P]
        for i, part in enumerate(PART_NAMES):
            sel = self.joint_part_ids == i
            if bool(sel.any()):
                out[part] = joints[:, sel].mean()
        return {k: float(v) for k, v in out.items()}


def refine_poses(
    avatar,
    images: Tensor,
    masks: Tensor,
    cameras: list,
    params: BodyParams,
    background: Tensor,
    config: PoseCorrectionConfig,
    steps: int,
    loss=None,
) -> tuple[BodyParams, PoseCorrection]:
    """Per-frame pose correction with the avatar frozen (a test-time refinement protocol).

    images: [T, H, W, 3] targets composited on ``background [3]``; masks: [T, H, W]; cameras: T
    ``Camera``; params: the T frames' fits. Every step renders every frame once. ``loss``: an
    ``AvatarLoss`` (default: L1 and the mask term). Returns the corrected parameters and the
    residuals.
    """
    from eva_engine.train.losses import AvatarLoss, LossConfig

    loss = loss or AvatarLoss(LossConfig(lambda_ssim=0.0, lambda_lpips=0.0))
    device = images.device
    n = params.batch_size
    correction = PoseCorrection(n, avatar.body.joint_part_ids[1:], params.expression.shape[1], config).to(
        device
    )
    opt = torch.optim.Adam(correction.parameters(), lr=config.lr)
    frozen = [p for p in avatar.parameters() if p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    try:
        for _ in range(steps):
            for t in range(n):
                render = avatar(correction.apply(params[t], t), cameras[t], background)
                total = loss(render, images[t], masks[t], key=t)["total"] + correction.prior(t)
                total.backward()
                opt.step()
                opt.zero_grad(set_to_none=True)
    finally:
        for p in frozen:
            p.requires_grad_(True)
    return correction.corrected(params), correction
