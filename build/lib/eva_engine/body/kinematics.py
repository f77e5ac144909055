"""Forward kinematics shared by the backends: per-joint axis-angle -> rigid LBS transforms.

Every joint rotates about its rest-pose head, in world-aligned axes of the rest pose (the SMPL-X
convention), so the transform of joint ``c`` is ``T_c = T_parent(c) @ [R_c | h_c - R_c h_c]`` and
the root's is ``[R_root | h_0 + transl - R_root h_0]``. All zero parameters give identities.
"""

from __future__ import annotations

from collections.abc import Sequence

import roma
import torch


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """[..., 3] axis-angle -> [..., 3, 3] rotation matrices. roma switches to a first-order
    expansion near zero, so values and gradients stay finite at exactly zero rotation."""
    return roma.rotvec_to_rotmat(rotvec)


def rigid(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] and [..., 3] -> [..., 4, 4] homogeneous transforms."""
    top = torch.cat([rotation, translation.unsqueeze(-1)], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


class KinematicTree:
    """The joint hierarchy in breadth-first levels, so forward kinematics costs one batched
    matrix product per depth level instead of one per joint.

    parents: [J] parent index per joint, the root (index 0) has a negative parent.
    """

    def __init__(self, parents: Sequence[int]) -> None:
        parents = [int(p) for p in parents]
        if parents[0] >= 0 or any(p < 0 for p in parents[1:]):
            raise ValueError("expected a single root joint at index 0")
        children: list[list[int]] = [[] for _ in parents]
        for j, p in enumerate(parents[1:], start=1):
            children[p].append(j)
        self.parents = parents
        self.levels: list[list[int]] = [[0]]
        # Position of each level's parents inside the previous level.
        self.parent_slots: list[list[int]] = [[0]]
        while True:
            prev = self.levels[-1]
            nxt = [c for j in prev for c in children[j]]
            if not nxt:
                break
            slot = {j: i for i, j in enumerate(prev)}
            self.levels.append(nxt)
            self.parent_slots.append([slot[parents[c]] for c in nxt])
        order = [j for level in self.levels for j in level]
        if sorted(order) != list(range(len(parents))):
            raise ValueError("every joint must descend from the root")
        self.inverse_order = torch.argsort(torch.tensor(order))

    def forward_kinematics(
        self,
        rotations: torch.Tensor,
        rest_heads: torch.Tensor,
        transl: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """LBS transforms and posed joint positions.

        rotations: [B, J, 3, 3] (row 0: the root's); rest_heads: [B, J, 3]; transl: [B, 3].
        Returns transforms [B, J, 4, 4] (rest -> posed) and joints [B, J, 3] (posed heads).
        """
        local_t = rest_heads - (rotations @ rest_heads.unsqueeze(-1)).squeeze(-1)
        local_t = torch.cat([local_t[:, :1] + transl[:, None], local_t[:, 1:]], dim=1)
        local = rigid(rotations, local_t)  # [B, J, 4, 4]
        chain = [local[:, self.levels[0]]]
        for level, slots in zip(self.levels[1:], self.parent_slots[1:], strict=True):
            chain.append(chain[-1][:, slots] @ local[:, level])
        transforms = torch.cat(chain, dim=1)[:, self.inverse_order.to(rest_heads.device)]
        joints = (transforms[..., :3, :3] @ rest_heads.unsqueeze(-1)).squeeze(-1) + transforms[..., :3, 3]
        return transforms, joints
