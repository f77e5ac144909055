"""Measuring a fit against ground truth: MPJPE of body and hand joints, and exact targets.

MPJPE is the mean 3D distance (mm) between fitted and true keypoints after removing the root:
body points relative to the hip centre, each hand's points relative to its wrist, so a global
depth error (unobservable up to scale from one camera) does not swamp the articulation error.
"""

from __future__ import annotations

import roma
import torch
from torch import Tensor

from eva_engine.align.targets import LEFT_HIP, POSE_BODY, RIGHT_HIP, FitTargets
from eva_engine.body import KEYPOINT_GROUPS, BodyModel, BodyParams
from eva_engine.geometry import project_points, to_camera


def targets_from_params(
    model: BodyModel,
    params: BodyParams,
    K: Tensor,
    viewmat: Tensor,
    image_size: tuple[int, int] | None = None,
) -> FitTargets:
    """What a perfect detector would report for a known clip: projected keypoints (confidence 1,
    0 outside ``image_size`` = (H, W) if given), hand depths and metric pose world landmarks."""
    with torch.no_grad():
        kp, _ = model.posed_keypoints(params)
        f = kp.shape[0]
        view = viewmat.expand(f, 4, 4) if viewmat.ndim == 2 else viewmat
        Ks = K.expand(f, 3, 3) if K.ndim == 2 else K
        cam = to_camera(kp, view)
        uv = project_points(cam, Ks)
        conf = torch.ones_like(uv[..., 0])
        if image_size is not None:
            h, w = image_size
            inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
            conf = inside.float()
        depth = []
        for group in ("left_hand", "right_hand"):
            sl = KEYPOINT_GROUPS[group]
            z = cam[:, sl, 2]
            depth.append((z - z[:, :1]) * Ks[:, 0, 0, None] / z[:, :1])
        body = kp[:, :33]
        hip = 0.5 * (body[:, LEFT_HIP] + body[:, RIGHT_HIP])
        world = (body - hip[:, None]) @ view[:, :3, :3].transpose(1, 2)
        pose_world = torch.cat([world, torch.ones_like(world[..., :1])], dim=-1)
        return FitTargets(torch.cat([uv, conf[..., None]], -1), K, viewmat, torch.cat(depth, 1), pose_world)


def mpjpe(
    model: BodyModel, params: BodyParams, truth: BodyParams, visible: Tensor | None = None
) -> dict[str, float]:
    """Root-relative mean per-joint position error in mm: ``body`` (MediaPipe's body joints,
    hip-centred) and ``hands`` (both hands' 21 points, each wrist-centred). With ``visible``
    ([F, K] bool, the keypoints inside the image), ``body_in_view`` averages only the body
    joints in view: a waist-up video says nothing about the legs. ``hands_rotation_aligned``: the
    hands' error after each fitted hand is turned about its wrist onto the truth (Kabsch), i.e.
    the fingers' articulation without the hand's orientation."""
    with torch.no_grad():
        a, _ = model.posed_keypoints(params)
        b, _ = model.posed_keypoints(truth)

        def body(kp: Tensor) -> Tensor:
            hip = 0.5 * (kp[:, LEFT_HIP] + kp[:, RIGHT_HIP])
            return kp[:, list(POSE_BODY)] - hip[:, None]

        def hands(kp: Tensor) -> Tensor:
            parts = [
                kp[:, KEYPOINT_GROUPS[g]] - kp[:, KEYPOINT_GROUPS[g].start][:, None]
                for g in ("left_hand", "right_hand")
            ]
            return torch.cat(parts, dim=1)

        body_err = (body(a) - body(b)).norm(dim=-1)
        ha, hb = hands(a), hands(b)
        out = {
            "body": float(body_err.mean() * 1000),
            "hands": float((ha - hb).norm(dim=-1).mean() * 1000),
            "hands_rotation_aligned": float(_rotation_aligned(ha, hb).mean() * 1000),
        }
        if visible is not None:
            seen = visible[:, list(POSE_BODY)].to(body_err.device)
            out["body_in_view"] = float(body_err[seen].mean() * 1000) if bool(seen.any()) else float("nan")
        return out


def _rotation_aligned(a: Tensor, b: Tensor) -> Tensor:
    """Distances [F, 42] between each wrist-centred hand of ``a`` turned onto ``b`` by its best
    rotation (Kabsch, no reflection) and ``b``. a, b: [F, 42, 3], both hands, 21 points each."""
    x, y = a.unflatten(1, (2, 21)), b.unflatten(1, (2, 21))  # [F, 2, 21, 3]
    u, _, vt = torch.linalg.svd(x.transpose(-1, -2) @ y)
    d = torch.linalg.det(u @ vt).sign()
    fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    turned = x @ (u @ fix @ vt)
    return (turned - y).norm(dim=-1).flatten(1)


def expression_error(model: BodyModel, params: BodyParams, truth: BodyParams, moved: float = 0.002) -> float:
    """Mean distance (mm) between the face vertices of the fitted and the true expression, on the
    true subject's rest face (pose and shape excluded: only what the facial actions do), over
    the vertices the true expression moves by more than ``moved`` metres. Expression
    coefficients themselves are not comparable: many facial actions move the face alike."""
    face = model.part_vertex_ids("face")
    with torch.no_grad():
        fitted = BodyParams(
            truth.root_orient, truth.transl, truth.joints, params.expression.to(truth.expression), truth.shape
        )
        neutral = BodyParams(
            truth.root_orient, truth.transl, truth.joints, torch.zeros_like(truth.expression), truth.shape
        )
        a, b, c = (model.canonical(p)[:, face] for p in (fitted, truth, neutral))
    active = (c - b).norm(dim=-1) > moved
    if not bool(active.any()):
        return 0.0
    return float((a - b).norm(dim=-1)[active].mean() * 1000)


EXPRESSION_GROUPS: dict[str, tuple[str, ...]] = {
    "jaw": ("jaw",),
    "lips": ("mouth",),
    "lids": ("eyeBlink", "eyeSquint", "eyeWide"),
    "brows": ("brow",),
}
"""Facial-action groups by name prefix (ARKit names): what :func:`expression_error_by_group` splits."""


def expression_error_by_group(model: BodyModel, params: BodyParams, truth: BodyParams) -> dict[str, float]:
    """{group: mm} :func:`expression_error` with only one ``EXPRESSION_GROUPS`` group's actions
    kept in both the fitted and the true expression (the others zeroed), and {group + "_neutral":
    mm} the same for a neutral fit: how much of each group's motion the fit recovers. NaN for a
    group the true expression never moves (or a model without such actions)."""
    out: dict[str, float] = {}
    names = list(model.expression_names)
    for group, prefixes in EXPRESSION_GROUPS.items():
        keep = torch.tensor([n.startswith(prefixes) for n in names], dtype=torch.bool)
        if not bool(keep.any()):
            out[group] = out[f"{group}_neutral"] = float("nan")
            continue

        def only(p: BodyParams, keep: Tensor = keep) -> BodyParams:
            e = p.expression * keep.to(p.expression)
            return BodyParams(p.root_orient, p.transl, p.joints, e, p.shape)

        t = only(truth)
        fitted = only(params.to(truth.expression))
        if float(t.expression.abs().max()) == 0.0:
            out[group] = out[f"{group}_neutral"] = float("nan")
            continue
        zero = BodyParams(t.root_orient, t.transl, t.joints, torch.zeros_like(t.expression), t.shape)
        out[group] = expression_error(model, fitted, t)
        out[f"{group}_neutral"] = expression_error(model, zero, t)
    return out


def head_rotation_delta(model: BodyModel, params: BodyParams, truth: BodyParams) -> Tensor:
    """[F, 3] per frame, the rotation from the true to the fitted world rotation of the head joint
    as a rotation vector (radians, world axes): where the fit turned the head, whatever the joints
    that turned it."""
    j = model.joint_names.index("head")
    with torch.no_grad():
        a = model(params).transforms[:, j, :3, :3]
        b = model(truth).transforms[:, j, :3, :3].to(a)
    return roma.rotmat_to_rotvec(a @ b.transpose(1, 2))


def head_rotation_error(model: BodyModel, params: BodyParams, truth: BodyParams) -> float:
    """Mean angle (degrees) of :func:`head_rotation_delta` over the frames."""
    return float(torch.rad2deg(head_rotation_delta(model, params, truth).norm(dim=-1)).mean())
