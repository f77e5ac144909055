"""Where the fit starts: the initial estimate from detections alone (inverse kinematics on
MediaPipe's world landmarks, the root facing the camera, translation by least squares) and the
hands turned to the detected palms."""

from __future__ import annotations

import dataclasses

import roma
import torch
from torch import Tensor

from eva_engine.align.hands import SIDES, hand_root_joints
from eva_engine.align.objective import FitProblem
from eva_engine.align.stages import FitConfig, FitStage
from eva_engine.align.targets import POSE_BODY, POSE_FACE, FitTargets, keypoint_mask
from eva_engine.body import KEYPOINT_GROUPS, BodyModel, BodyParams
from eva_engine.geometry import MIN_DEPTH, to_camera


def facing_camera_root(viewmat: Tensor) -> Tensor:
    """[F, 3] root axis-angle (a turn about +Y) that makes a subject facing +Z face the camera."""
    forward = viewmat[..., 2, :3]  # camera z axis in world coordinates
    yaw = torch.atan2(-forward[..., 0], -forward[..., 2])
    return torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], dim=-1)


def solve_translation(model: BodyModel, params: BodyParams, targets: FitTargets, default_depth: float = 3.0):
    """[F, 3] world translations that best align the posed body's pose keypoints with the 2D
    detections (weighted linear least squares per frame, the rotation held fixed).

    With camera-frame points Y = R X + t_v and unknown u = R t: x_n (Y_z + u_z) = Y_x + u_x and
    likewise for y, linear in u. Frames with fewer than 3 confident points take the clip's median.
    """
    with torch.no_grad():
        zero = dataclasses.replace(params, transl=torch.zeros_like(params.transl))
        kp, _ = model.posed_keypoints(zero)
        view, K = targets.frame_viewmat(), targets.frame_K()
        Y = to_camera(kp[:, :33], view)  # [F, 33, 3]
        det = targets.keypoints[:, :33]
        w = det[..., 2] * keypoint_mask(33, POSE_BODY + POSE_FACE)
        xn = (det[..., 0] - K[:, None, 0, 2]) / K[:, None, 0, 0]
        yn = (det[..., 1] - K[:, None, 1, 2]) / K[:, None, 1, 1]
        zeros, ones = torch.zeros_like(xn), torch.ones_like(xn)
        rows = torch.cat(
            [torch.stack([ones, zeros, -xn], -1), torch.stack([zeros, ones, -yn], -1)], dim=1
        )  # [F, 66, 3]
        rhs = torch.cat([xn * Y[..., 2] - Y[..., 0], yn * Y[..., 2] - Y[..., 1]], dim=1)  # [F, 66]
        sw = torch.cat([w, w], dim=1).sqrt()
        A = rows * sw[..., None]
        b = rhs * sw
        ata = A.transpose(1, 2) @ A + 1e-6 * torch.eye(3)
        u = torch.linalg.solve(ata, (A.transpose(1, 2) @ b[..., None]))[..., 0]  # [F, 3]
        enough = (w > 0.3).sum(1) >= 3
        centre_z = Y[..., 2].mean(1)
        fallback = torch.tensor([0.0, 0.0, default_depth]) - Y.mean(1)
        u = torch.where(enough[:, None], u, u[enough].median(0).values if enough.any() else fallback)
        # Keep the body in front of the camera.
        u[:, 2] = torch.maximum(u[:, 2], 0.5 - centre_z)
        return (u[:, None, :] @ view[:, :3, :3])[:, 0]  # t = R^T u


def initial_estimate(model: BodyModel, targets: FitTargets, config: FitConfig | None = None) -> BodyParams:
    """The starting point from detections alone: body pose by inverse kinematics on MediaPipe's
    metric world landmarks (L-BFGS on the robust 3D term, root and body joints), the root
    facing the camera where nothing better is known, then translation by least squares."""
    config = config or FitConfig()
    f = targets.num_frames
    params = model.default_params(f)
    params.root_orient.copy_(facing_camera_root(targets.frame_viewmat()))
    if targets.pose_world is not None and config.ik_iterations > 0:
        ik = FitStage("ik", config.ik_iterations, ("root", "body"), w_pose=0.0, body_3d=1.0, smooth=0.01)
        problem = FitProblem(model, targets, config, params)
        problem.run_stage(ik, None)
        params = problem.params().map(lambda t: t.detach().clone())
    params.transl.copy_(solve_translation(model, params, targets))
    if config.orient_hands and targets.hand_depth is not None:
        params = orient_hands(model, params, targets, config.hand_depth_scale)
    return params


PALM = (0, 5, 9, 13, 17)  # wrist and the four finger knuckles: rigid with the wrist bone


def orient_hands(model: BodyModel, params: BodyParams, targets: FitTargets, depth_scale: float) -> BodyParams:
    """``params`` with each detected hand's wrist joint turned so that the model's palm points
    (wrist, knuckles; camera frame, relative to the wrist) best align in rotation with the
    detected palm lifted to 3D by MediaPipe's relative depths (Kabsch). Other frames unchanged."""
    out = params.map(lambda t: t.detach().clone())
    with torch.no_grad():
        posed = model(out)
        kp = model.keypoints(posed)
        view, K = targets.frame_viewmat(), targets.frame_K()
        cam = to_camera(kp, view)
        for side, offset, wrist in zip(SIDES, (0, 21), hand_root_joints(model), strict=True):
            idx = [KEYPOINT_GROUPS[side].start + i for i in PALM]
            det = targets.keypoints[:, idx]
            ok = (det[..., 2] > 0).all(dim=1)
            if not bool(ok.any()):
                continue
            z = cam[:, idx[0], 2:3].clamp_min(MIN_DEPTH)  # [F, 1] the model wrist's depth
            x = (det[..., 0] - det[:, :1, 0]) / K[:, None, 0, 0] * z
            y = (det[..., 1] - det[:, :1, 1]) / K[:, None, 1, 1] * z
            dz = depth_scale * targets.hand_depth[:, [offset + i for i in PALM]] * z / K[:, None, 0, 0]
            target = torch.stack([x, y, dz], dim=-1).double()  # [F, 5, 3]
            model_pts = (cam[:, idx] - cam[:, idx[:1]]).double()
            cov = model_pts.transpose(1, 2) @ target  # [F, 3, 3]
            u, _, vt = torch.linalg.svd(cov)
            d = torch.sign(torch.linalg.det(vt.transpose(1, 2) @ u.transpose(1, 2)))
            fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
            r_cam = vt.transpose(1, 2) @ fix @ u.transpose(1, 2)  # model -> detected, camera frame
            v = view[:, :3, :3].double()
            r_world = v.transpose(1, 2) @ r_cam @ v
            g = posed.transforms[:, wrist, :3, :3].double()
            g_parent = posed.transforms[:, int(model.parents[wrist]), :3, :3].double()
            local = g_parent.transpose(1, 2) @ r_world @ g
            rotvec = roma.rotmat_to_rotvec(local).to(out.joints.dtype)
            out.joints[ok, wrist - 1] = rotvec[ok]
    return out
