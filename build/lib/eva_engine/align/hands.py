"""Hands through the whole clip: reject detections on the wrong hand, and fill the frames where a
hand was not found from its neighbours in pose space, with a confidence that says so.

MediaPipe finds a hand in only part of the frames of a real video (hands at the frame's edge,
small, blurred, fists). A frame without its hand's detection keeps, after fitting, whatever the
smoothness term and the pull toward the initial estimate left there: a rest-pose hand that is
wrong in every such frame. Between two frames where the hand was found, its pose is better
estimated by interpolating the fitted hand joints (rotation slerp per joint, the wrist
included), with a confidence that falls from 1 at a detection to ``min_confidence`` in the
middle of the longest gap filled; gaps longer than ``max_gap`` seconds, and the clip's ends
before the first / after the last detection, are left as fitted with confidence 0.

Holistic assigns a hand to the body's left or right by proximity; when it gets that wrong, the
hand's points pull the fit's other hand across the body. A detection whose wrist is farther from
its own side's pose wrist than from the other side's, or farther than ``max_wrist_offset``
palm-sizes from its own, is dropped (confidence 0) before fitting.
"""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch
from torch import Tensor

from eva_engine.body import KEYPOINT_GROUPS, PART_NAMES, BodyModel, BodyParams

POSE_WRIST = {"left_hand": 15, "right_hand": 16}
SIDES = ("left_hand", "right_hand")


@dataclass(frozen=True)
class HandTrackConfig:
    """max_wrist_offset: palm sizes between a hand's detected wrist and its pose wrist beyond
    which the detection is dropped; max_gap: longest gap (seconds) filled by interpolation;
    min_confidence: the confidence in the middle of a gap of ``max_gap``."""

    max_wrist_offset: float = 1.5
    max_gap: float = 1.0
    min_confidence: float = 0.3


def hand_found(keypoints: Tensor) -> Tensor:
    """[F, 2] bool: the left / right hand was detected (its points have confidence > 0)."""
    return torch.stack([keypoints[:, KEYPOINT_GROUPS[s], 2].amax(1) > 0 for s in SIDES], dim=1)


def reject_wrong_hands(keypoints: Tensor, config: HandTrackConfig | None = None) -> tuple[Tensor, Tensor]:
    """keypoints [F, K, 3] -> (keypoints with wrong-side hand detections zeroed, [F, 2] bool of
    the rejections). A hand is judged against the pose model's wrists, which Holistic tracks
    on every frame the person is found."""
    config = config or HandTrackConfig()
    kp = keypoints.clone()
    rejected = torch.zeros(kp.shape[0], 2, dtype=torch.bool)
    for h, side in enumerate(SIDES):
        other = SIDES[1 - h]
        sl = KEYPOINT_GROUPS[side]
        hand = kp[:, sl]
        found = hand[..., 2].amax(1) > 0
        wrist = hand[:, 0, :2]
        own, opposite = kp[:, POSE_WRIST[side]], kp[:, POSE_WRIST[other]]
        palm = (hand[:, 9, :2] - wrist).norm(dim=-1).clamp_min(1.0)  # wrist -> middle knuckle
        d_own = (wrist - own[:, :2]).norm(dim=-1)
        d_opp = (wrist - opposite[:, :2]).norm(dim=-1)
        poses = (own[:, 2] > 0) & (opposite[:, 2] > 0)
        wrong = found & poses & ((d_opp < d_own) | (d_own > config.max_wrist_offset * palm))
        kp[wrong, sl, 2] = 0.0
        rejected[:, h] = wrong
    return kp, rejected


def hand_joint_sides(model: BodyModel) -> tuple[Tensor, Tensor]:
    """(left, right): indices into ``pose_joint_names`` of each hand's joints (hand-part joints,
    sided by their rest position: the subject's left is +X)."""
    with torch.no_grad():
        x = model(model.default_params(1)).joints[0, 1:, 0]
    hand = model.joint_part_ids[1:].cpu() == PART_NAMES.index("hand")
    x = x.cpu()
    return torch.nonzero(hand & (x > 0)).squeeze(1), torch.nonzero(hand & (x <= 0)).squeeze(1)


def hand_root_joints(model: BodyModel) -> tuple[int, int]:
    """(left, right) joint index (into ``joint_names``) of each hand's root: its hand-part joint
    whose parent is not a hand joint (the wrist)."""
    out = []
    parents = model.parents.cpu()
    hand = model.joint_part_ids.cpu() == PART_NAMES.index("hand")
    for joints in hand_joint_sides(model):
        ids = (joints + 1).tolist()  # pose joint -> joint index
        roots = [j for j in ids if not bool(hand[int(parents[j])])]
        if len(roots) != 1:
            raise ValueError(f"a hand has {len(roots)} root joints; expected one wrist")
        out.append(roots[0])
    return out[0], out[1]


def fill_hand_gaps(
    model: BodyModel,
    params: BodyParams,
    found: Tensor,
    times: Tensor,
    config: HandTrackConfig | None = None,
) -> tuple[BodyParams, Tensor]:
    """Interpolate each hand's joints over the frames where it was not found (module docstring).

    params: the fitted clip (F rows); found: [F, 2] bool (left, right); times: [F] seconds.
    Returns the filled parameters and the hands' confidence [F, 2] in [0, 1].
    """
    config = config or HandTrackConfig()
    out = params.map(lambda t: t.detach().clone())
    confidence = found.float().clone()
    times = torch.as_tensor(times, dtype=torch.float64)
    for h, joints in enumerate(hand_joint_sides(model)):
        seen = torch.nonzero(found[:, h]).squeeze(1).tolist()
        for a, b in zip(seen[:-1], seen[1:], strict=True):
            if b - a < 2:
                continue
            gap = float(times[b] - times[a])
            if gap > config.max_gap:
                continue
            ra = roma.rotvec_to_unitquat(out.joints[a, joints].double())
            rb = roma.rotvec_to_unitquat(out.joints[b, joints].double())
            for i in range(a + 1, b):
                s = float((times[i] - times[a]) / max(gap, 1e-9))
                q = roma.unitquat_slerp(ra, rb, torch.tensor([s], dtype=torch.float64))[0]
                out.joints[i, joints] = roma.unitquat_to_rotvec(q).to(out.joints.dtype)
                # 1 next to a detection, down to min_confidence mid-way through a gap of max_gap.
                depth = min(s, 1.0 - s) * 2.0 * gap / config.max_gap
                confidence[i, h] = 1.0 - (1.0 - config.min_confidence) * depth
    return out, confidence


@dataclass(frozen=True)
class ArticulationPrior:
    """Which rotation components of the hand joints are anatomically implausible: for joint
    ``joints[m]`` (pose-joint index), the penalised part of its axis-angle r is
    ``projectors[m] @ r``, weighed by ``weights[m]``."""

    joints: Tensor  # [M] int64
    projectors: Tensor  # [M, 3, 3]
    weights: Tensor  # [M]

    def penalty(self, rotvecs: Tensor) -> Tensor:
        """The weighted squared implausible parts, mean over frames and these joints; rotvecs:
        [F, P, 3] pose joints."""
        off_axis = (self.projectors @ rotvecs[:, self.joints, :, None]).squeeze(-1)  # [F, M, 3]
        return (self.weights * off_axis.square().sum(-1)).mean()


def articulation_prior(model: BodyModel, metacarpal_weight: float = 0.3) -> ArticulationPrior:
    """The hand's joint types from the rest skeleton, for any body model with finger chains.

    Each chain from the wrist ends in three finger joints: MCP (flexion and abduction; its
    twist about the finger is penalised), PIP and DIP (hinges: everything but flexion is
    penalised); for the thumb (the chain whose first finger joint is nearest the wrist) CMC is
    free, MCP loses its twist, IP is a hinge. Joints before the last three of a chain (Anny's
    metacarpals) barely move in a real hand: all of their rotation is penalised, with
    ``metacarpal_weight``. Flexion axes are
    finger direction x palm normal in the rest pose (the kinematics rotate about world-aligned
    axes at the rest heads, so rest-frame axes are the rotation vectors' axes).
    """
    with torch.no_grad():
        heads = model(model.default_params(1)).joints[0].double().cpu()
    parents = model.parents.cpu().tolist()
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(p, []).append(j)
    joints, projectors, weights = [], [], []
    eye = torch.eye(3, dtype=torch.float64)
    for wrist in hand_root_joints(model):
        chains = []
        for start in children.get(wrist, []):
            chain = [start]
            while len(children.get(chain[-1], [])) == 1:
                chain.append(children[chain[-1]][0])
            chains.append(chain)
        if len(chains) < 5:
            raise ValueError(f"hand root {wrist} has {len(chains)} finger chains; expected 5")
        # The thumb's first finger joint (CMC) sits near the wrist, the others' (knuckles) do not.
        thumb = min(chains, key=lambda c: float((heads[c[-3]] - heads[wrist]).norm()))
        fingers = [c for c in chains if c is not thumb]
        knuckles = torch.stack([heads[c[-3]] for c in fingers])
        across = knuckles[(knuckles - knuckles.mean(0)).norm(dim=1).argmax()] - knuckles.mean(0)
        palm_normal = torch.linalg.cross(knuckles.mean(0) - heads[wrist], across)
        palm_normal = palm_normal / palm_normal.norm()
        for chain in chains:
            for k, j in enumerate(chain):
                role = len(chain) - k  # 3 = MCP (CMC for the thumb), 2 = PIP, 1 = DIP
                child = chain[k + 1] if k + 1 < len(chain) else None
                tip = heads[child] if child is not None else heads[j] + (heads[j] - heads[parents[j]])
                d = (tip - heads[j]) / (tip - heads[j]).norm()
                flex = torch.linalg.cross(d, palm_normal)
                flex = flex / flex.norm()
                if role > 3:  # metacarpal
                    proj, w = eye, metacarpal_weight
                elif role == 3:  # MCP: no twist; the thumb's CMC: free
                    if chain is thumb:
                        continue
                    proj, w = torch.outer(d, d), 1.0
                elif role == 2 and chain is thumb:  # thumb MCP: no twist
                    proj, w = torch.outer(d, d), 1.0
                else:  # PIP, DIP, thumb IP: hinges
                    proj, w = eye - torch.outer(flex, flex), 1.0
                joints.append(j - 1)  # pose joints exclude the root
                projectors.append(proj)
                weights.append(w)
    return ArticulationPrior(
        torch.tensor(joints, dtype=torch.int64),
        torch.stack(projectors).float(),
        torch.tensor(weights, dtype=torch.float32),
    )
