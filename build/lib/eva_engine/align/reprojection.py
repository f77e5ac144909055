"""How far the fitted keypoints land from the detections, in pixels."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from eva_engine.align.targets import POSE_BODY, FitTargets
from eva_engine.body import KEYPOINT_GROUPS, BodyModel, BodyParams
from eva_engine.geometry import project_points, to_camera


def reprojection_distances(model: BodyModel, params: BodyParams, targets: FitTargets) -> Tensor:
    """[F, K] 2D distance in pixels between each model keypoint and its detection (whatever the
    detection's confidence)."""
    with torch.no_grad():
        kp, _ = model.posed_keypoints(params)
        uv = project_points(to_camera(kp, targets.frame_viewmat()), targets.frame_K())
        return (uv - targets.keypoints[..., :2]).norm(dim=-1)


def reprojection_error(model: BodyModel, params: BodyParams, targets: FitTargets) -> dict[str, float]:
    """Median 2D distance in pixels between model keypoints and confident detections, per group
    (body = the pose body joints, left/right hand, face); NaN where nothing was detected."""
    dist = reprojection_distances(model, params, targets)
    ok = targets.keypoints[..., 2] > 0.5
    groups = {
        "body": torch.tensor(POSE_BODY),
        "hands": torch.arange(KEYPOINT_GROUPS["left_hand"].start, KEYPOINT_GROUPS["right_hand"].stop),
        "face": torch.arange(KEYPOINT_GROUPS["face"].start, KEYPOINT_GROUPS["face"].stop),
    }
    out = {}
    for name, idx in groups.items():
        d = dist[:, idx][ok[:, idx]]
        out[name] = float(d.median()) if d.numel() else math.nan
    return out
