"""The keypoint layout every body model produces, matching MediaPipe holistic's output.

``KEYPOINT_NAMES`` (K = 91), in this order:

- 33 pose landmarks, MediaPipe Pose/BlazePose order and names (``nose`` ... ``right_foot_index``);
- 21 left-hand landmarks then 21 right-hand landmarks, MediaPipe Hands order, named
  ``left_hand_wrist``, ``left_hand_thumb_cmc`` ... ``right_hand_pinky_tip``;
- 16 face points, each one landmark of MediaPipe's 478-point face mesh (``FACE_MESH_INDEX``):
  eye corners, eyelid centres, iris centres, nose tip, mouth corners, inner lip centres and chin
  -- the points a smooth body mesh and the face mesh both define without texture (brows and the
  jaw contour are left out: on the mesh they are not geometric features).

"left"/"right" are the subject's (MediaPipe's holistic convention), i.e. world +X is left.
Each backend defines the points as a fixed sparse linear map of its posed vertices and joints
(:class:`KeypointRegressor`), documented in the backend module.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

POSE_NAMES = (
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)
# One line per finger, base to tip.
# fmt: off
HAND_NAMES = (
    "wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_finger_mcp", "index_finger_pip", "index_finger_dip", "index_finger_tip",
    "middle_finger_mcp", "middle_finger_pip", "middle_finger_dip", "middle_finger_tip",
    "ring_finger_mcp", "ring_finger_pip", "ring_finger_dip", "ring_finger_tip",
    "pinky_mcp", "pinky_pip", "pinky_dip", "pinky_tip",
)
# fmt: on
FACE_MESH_INDEX: Mapping[str, int] = {
    "face_right_eye_outer": 33,
    "face_right_eye_inner": 133,
    "face_left_eye_inner": 362,
    "face_left_eye_outer": 263,
    "face_right_eye_upper_lid": 159,
    "face_right_eye_lower_lid": 145,
    "face_left_eye_upper_lid": 386,
    "face_left_eye_lower_lid": 374,
    "face_right_iris": 468,
    "face_left_iris": 473,
    "face_nose_tip": 1,
    "face_mouth_right": 61,
    "face_mouth_left": 291,
    "face_upper_lip_inner": 13,
    "face_lower_lip_inner": 14,
    "face_chin": 152,
}
"""Face keypoint name -> index in MediaPipe's face mesh (468 + 10 iris points, refined)."""

FACE_NAMES = tuple(FACE_MESH_INDEX)
KEYPOINT_NAMES = (
    POSE_NAMES
    + tuple(f"left_hand_{n}" for n in HAND_NAMES)
    + tuple(f"right_hand_{n}" for n in HAND_NAMES)
    + FACE_NAMES
)
KEYPOINT_GROUPS: Mapping[str, slice] = {
    "pose": slice(0, 33),
    "left_hand": slice(33, 54),
    "right_hand": slice(54, 75),
    "face": slice(75, 91),
}
"""Where each detector output lands in the layout."""


class KeypointRegressor(torch.nn.Module):
    """keypoints = W_v @ vertices + W_j @ joints with fixed sparse W_v [K, V] and dense W_j [K, J].

    Every row of ``[W_v, W_j]`` sums to 1, so keypoints move rigidly with the body.
    """

    def __init__(
        self,
        names: Sequence[str],
        vertex_terms: Mapping[str, Mapping[int, float]],
        joint_terms: Mapping[str, Mapping[int, float]],
        num_joints: int,
    ) -> None:
        super().__init__()
        self.names = list(names)
        rows, cols, vals = [], [], []
        w_j = torch.zeros(len(self.names), num_joints, dtype=torch.float64)
        for k, name in enumerate(self.names):
            vt, jt = vertex_terms.get(name, {}), joint_terms.get(name, {})
            total = sum(vt.values()) + sum(jt.values())
            if not vt and not jt or abs(total - 1.0) > 1e-4:
                raise ValueError(f"keypoint {name!r} weights sum to {total}, expected 1")
            for v, w in vt.items():
                rows.append(k)
                cols.append(int(v))
                vals.append(float(w))
            for j, w in jt.items():
                w_j[k, int(j)] += float(w)
        self.register_buffer("vertex_rows", torch.tensor(rows, dtype=torch.int64), persistent=False)
        self.register_buffer("vertex_cols", torch.tensor(cols, dtype=torch.int64), persistent=False)
        self.register_buffer("vertex_weights", torch.tensor(vals, dtype=torch.float32), persistent=False)
        self.register_buffer("joint_weights", w_j.float(), persistent=False)

    def forward(self, vertices: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """vertices: [B, V, 3]; joints: [B, J, 3] -> keypoints [B, K, 3]."""
        b, v = vertices.shape[:2]
        # Rows sum to 1, so regress offsets from the root joint: float32 sums of thousands of
        # terms (Anny's ear regressors) then do not lose precision to a large translation.
        origin = joints[:, :1].detach()
        w_v = torch.sparse_coo_tensor(
            torch.stack([self.vertex_rows, self.vertex_cols]),
            self.vertex_weights.to(vertices.dtype),
            (len(self.names), v),
            check_invariants=False,  # valid by construction
        )
        flat = (vertices - origin).permute(1, 0, 2).reshape(v, b * 3)  # [V, B*3]
        from_vertices = torch.sparse.mm(w_v, flat).view(-1, b, 3).transpose(0, 1)
        from_joints = torch.einsum("kj,bjc->bkc", self.joint_weights.to(joints.dtype), joints - origin)
        return from_vertices + from_joints + origin

    def dense_vertex_weights(self, num_vertices: int) -> torch.Tensor:
        """W_v as a dense [K, V] tensor (for inspection and tests)."""
        w = torch.zeros(len(self.names), num_vertices, dtype=self.vertex_weights.dtype)
        w.index_put_(
            (self.vertex_rows.cpu(), self.vertex_cols.cpu()), self.vertex_weights.cpu(), accumulate=True
        )
        return w
