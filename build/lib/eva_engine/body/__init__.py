"""Parametric body models behind one interface: Anny (embedded default) and SMPL-X (bring your
own files). Nothing outside this package knows which backend it is talking to.

    from eva_engine.body import load_body_model
    model = load_body_model("anny")
    params = model.params_from_pose({"joints": {"lowerarm01.L": [0, 0, -1.2]}})
    out = model(params)                      # BodyOutput(vertices, joints, transforms)
    kp = model.keypoints(out)                # [B, 91, 3], layout: body.keypoints.KEYPOINT_NAMES

World convention: Y up, the subject faces +Z, metres (see ``body.model``).
"""

from __future__ import annotations

from eva_engine.body.anny_cache import AnnyCacheError, ensure_anny_cache, prepare_anny_cache
from eva_engine.body.keypoints import (
    FACE_MESH_INDEX,
    HAND_NAMES,
    KEYPOINT_GROUPS,
    KEYPOINT_NAMES,
    POSE_NAMES,
)
from eva_engine.body.model import (
    PART_NAMES,
    SIDED_PART_NAMES,
    BodyModel,
    BodyOutput,
    lbs,
    nearest_vertex_index,
    nearest_vertex_weights,
)
from eva_engine.body.params import BodyParams, BodyPose, InvalidPoseError

BACKENDS = ("anny", "smplx")


def load_body_model(name: str = "anny", **options) -> BodyModel:
    """The one way to get a body model.

    ``"anny"`` options: see ``AnnyConfig`` (``cache_dir``, ``build_cache``).
    ``"smplx"`` options: see ``SmplxConfig`` (``model_path`` or ``$EVA_SMPLX_DIR``, ``gender``,
    ``num_betas``, ``num_expression_coeffs``, ``pose_correctives``).
    The model is float32 on CPU; move it with ``.to(device)``.
    """
    if name == "anny":
        from eva_engine.body.anny_backend import AnnyBody, AnnyConfig

        return AnnyBody(AnnyConfig(**options))
    if name == "smplx":
        from eva_engine.body.smplx_backend import SmplxBody, SmplxConfig

        return SmplxBody(SmplxConfig(**options))
    raise ValueError(f"unknown body model {name!r}; choose one of {BACKENDS}")


__all__ = [
    "BACKENDS",
    "FACE_MESH_INDEX",
    "HAND_NAMES",
    "KEYPOINT_GROUPS",
    "KEYPOINT_NAMES",
    "PART_NAMES",
    "SIDED_PART_NAMES",
    "POSE_NAMES",
    "AnnyCacheError",
    "BodyModel",
    "BodyOutput",
    "BodyParams",
    "BodyPose",
    "InvalidPoseError",
    "ensure_anny_cache",
    "lbs",
    "load_body_model",
    "nearest_vertex_index",
    "nearest_vertex_weights",
    "prepare_anny_cache",
]
