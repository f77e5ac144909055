"""The body's articulation prior: how Anny's redundant bones may turn.

Anny's skeleton has more bones than a person has free joints: the upper arm and the forearm are
two bones each, the spine five, the neck three, and a clavicle and a shoulder bone sit between
the chest and the arm. Keypoints fix where the joints are, not which of these bones turns to put
them there; left free, a fit spreads a shoulder's raise over the clavicle, the shoulder bone and
both upper-arm bones, differently in each frame. The joints still land on the detections, but the
skin between them slides from frame to frame, and an avatar trained on those frames blurs what
is drawn on it.

The prior follows the anatomy, as ``hands.articulation_prior`` does for the fingers:

- the second bone of the upper arm and of the forearm only twist about their own axis (a humerus
  does not bend half-way; the forearm's second bone carries its pronation);
- the elbow is a hinge about its rest axis (``body.rest_axes``);
- the clavicle and the shoulder bone, the spine's and the neck's segments move little: all of
  their rotation is penalised, lightly (a bend shared evenly by a chain costs least, so the
  spine and neck bend along their length instead of at one segment).

Built for Anny's bone names; a body model without them (SMPL-X) gets an empty prior.

An option (``FitStage.body_prior``), off in every default stage: on the synthetic close-up it
steadies the chest's skin and sharpens the avatar, on real video the fit lands further from the
detections and two of three clips' avatars get worse (``bench/results/body_prior/``,
``docs/alignment.md``, "The body's redundant bones").
"""

from __future__ import annotations

import numpy as np
import torch

from eva_engine.align.hands import ArticulationPrior
from eva_engine.body import BodyModel
from eva_engine.body.rest_axes import rest_axes

SEGMENT_BONES = ("clavicle", "shoulder01")
"""Bones between the chest and the arm, per side (``.L`` / ``.R``)."""
CHAIN_BONES = ("spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "neck02", "neck03")


def body_articulation_prior(
    model: BodyModel, shape: torch.Tensor | None = None, segment_weight: float = 0.3
) -> ArticulationPrior:
    """The prior over the pose joints of ``model`` (module docstring). Axes come from the rest
    skeleton of ``shape`` [1, S] (``body.rest_axes``; None: the default shape); the kinematics
    rotate about world-aligned axes at the rest heads, so rest axes are the rotation vectors'
    axes. The subject's own shape matters: an elbow's hinge is a few degrees off between body
    shapes, and at a right angle of flexion that is a sideways bend the prior would fight.
    ``segment_weight``: the weight of the clavicle, shoulder, spine and neck bones' whole
    rotation, relative to the arm bones' off-axis part (1)."""
    names = list(model.joint_names)
    arm = ("upperarm01", "upperarm02", "lowerarm01", "lowerarm02", "wrist")
    needed = [f"{b}.{s}" for b in arm for s in "LR"]
    if any(n not in names for n in needed):
        empty = torch.zeros(0, 3, 3)
        return ArticulationPrior(torch.zeros(0, dtype=torch.int64), empty, torch.zeros(0))
    axes = rest_axes(model, (shape if shape is not None else model.default_params(1).shape).detach())
    if not all(np.isfinite(a[s]).all() for a in (axes.upper_arm, axes.forearm, axes.elbow) for s in "LR"):
        raise ValueError("the rest skeleton's arm is straight or degenerate: no elbow axis")
    eye = torch.eye(3, dtype=torch.float64)

    def along(axis: np.ndarray) -> torch.Tensor:
        """The projector that keeps all but the turn about ``axis``."""
        a = torch.as_tensor(axis, dtype=torch.float64)
        return eye - torch.outer(a, a)

    joints, projectors, weights = [], [], []

    def add(name: str, projector: torch.Tensor, weight: float) -> None:
        if name in names:
            joints.append(names.index(name) - 1)  # pose joints exclude the root
            projectors.append(projector)
            weights.append(weight)

    for s in "LR":
        add(f"upperarm02.{s}", along(axes.upper_arm[s]), 1.0)
        add(f"lowerarm01.{s}", along(axes.elbow[s]), 1.0)
        add(f"lowerarm02.{s}", along(axes.forearm[s]), 1.0)
        for bone in SEGMENT_BONES:
            add(f"{bone}.{s}", eye, segment_weight)
    for bone in CHAIN_BONES:
        add(bone, eye, segment_weight)
    return ArticulationPrior(
        torch.tensor(joints, dtype=torch.int64),
        torch.stack(projectors).float(),
        torch.tensor(weights, dtype=torch.float32),
    )
