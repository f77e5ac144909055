"""The fit's objective over one clip (``FitProblem``): every term of ``align.fit``'s module
docstring, over parameter groups a stage moves or holds, minimised stage by stage with L-BFGS."""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from eva_engine.align.body_prior import body_articulation_prior
from eva_engine.align.bounded_lbfgs import minimize_bounded
from eva_engine.align.face_calibration import EYE_CORNERS, load_calibration
from eva_engine.align.face_mesh import OPENING_PAIRS, load_correspondence, shared_painted_face
from eva_engine.align.hands import articulation_prior
from eva_engine.align.robust import weighted_gm, z_only_gm
from eva_engine.align.silhouette import (
    SilhouetteTargets,
    silhouette_loss,
    silhouette_vertices,
)
from eva_engine.align.stages import FitConfig, FitStage
from eva_engine.align.targets import (
    LEFT_HIP,
    POSE_BODY,
    POSE_FACE,
    POSE_HAND,
    RIGHT_HIP,
    FitTargets,
    keypoint_mask,
)
from eva_engine.body import KEYPOINT_GROUPS, PART_NAMES, BodyModel, BodyParams
from eva_engine.body.keypoints import KeypointRegressor
from eva_engine.body.kinematics import axis_angle_to_matrix
from eva_engine.geometry import MIN_DEPTH, mean_neighbour_distance, project_points, to_camera
from eva_engine.progress import Progress, ProgressEvent

# Rotation-angle limits (radians) of one joint, per part: generous ranges that rule out
# impossible twists (a finger bent 150 degrees, a head turned backwards) but no real pose.
JOINT_LIMITS = {"body": 2.4, "hand": 1.75, "face": 0.9}


class FitProblem:
    """The objective over one clip; parameters split into groups so a stage can move a subset."""

    def __init__(self, model: BodyModel, targets: FitTargets, config: FitConfig, init: BodyParams):
        self.model, self.targets, self.config = model, targets, config
        self.init = init.map(lambda t: t.detach().clone())
        part = model.joint_part_ids[1:].cpu()  # pose joints exclude the root
        self.joint_index = {p: torch.nonzero(part == i).squeeze(1) for i, p in enumerate(PART_NAMES)}
        self.values: dict[str, Tensor] = {
            "expression": init.expression.detach().clone(),
            "shape": init.shape[:1].detach().clone(),
        }
        self.set_params(init)
        self.K = targets.frame_K()
        self.viewmat = targets.frame_viewmat()
        self.scale = targets.person_scale()
        kp = targets.keypoints
        self.conf = kp[..., 2]
        face = KEYPOINT_GROUPS["face"]
        self.group_mask = {
            "pose": keypoint_mask(kp.shape[1], POSE_BODY),
            "pose_face": keypoint_mask(kp.shape[1], POSE_FACE),
            "pose_hand": keypoint_mask(kp.shape[1], POSE_HAND),
            "hand": keypoint_mask(
                kp.shape[1], range(KEYPOINT_GROUPS["left_hand"].start, KEYPOINT_GROUPS["right_hand"].stop)
            ),
            "face": keypoint_mask(kp.shape[1], range(face.start, face.stop)),
        }
        self.group_mask["face_rigid"] = self.group_mask["face"] * rigid_face_points(model).float()
        self.face_missing = ((self.conf * self.group_mask["face"]).sum(1) == 0).float()  # [F]
        limits = torch.tensor([JOINT_LIMITS[p] for p in PART_NAMES])
        self.joint_limit = limits[part]  # [P]
        uses_prior = any(s.hand_prior > 0 for s in config.stages)
        self.articulation = articulation_prior(model) if uses_prior else None
        self.body_articulation = None  # built per stage for the current shape (run_stage)
        self.face_mesh = None  # (regressor, landmark indices) of the dense face term
        self.opening_pairs = None  # [2, Q] positions in those landmark indices
        self.calibration = None  # what the detector reads beyond those points, in their order
        dense = config.dense_face and targets.face_mesh is not None
        if dense and any(s.w_face_mesh > 0 or s.w_openings > 0 or s.face_z > 0 for s in config.stages):
            with shared_painted_face(model) as renderer:  # opened only where a cache is missing
                corr = load_correspondence(model, renderer=renderer)
                use = corr is not None and config.detector_calibration
                calibration = load_calibration(model, corr, renderer=renderer) if use else None
            if corr is not None:
                self.face_mesh = corr.regressor(model)
                at = {int(k): i for i, k in enumerate(self.face_mesh[1])}
                pairs = [(at[a], at[b]) for a, b in OPENING_PAIRS if a in at and b in at]
                self.opening_pairs = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2).T
                if calibration is not None:
                    self.calibration = calibration.aligned(self.face_mesh[1])
        self.silhouette = None  # (regressor of the outline's vertices, SilhouetteTargets, spacing m)
        if targets.person_masks is not None and any(s.w_silhouette > 0 for s in config.stages):
            self.silhouette = _silhouette_problem(model, targets.person_masks, config.silhouette_points)

    def params(self) -> BodyParams:
        v = self.values
        f = self.targets.num_frames
        joints = self.init.joints.new_zeros(f, self.init.joints.shape[1], 3)
        for p, idx in self.joint_index.items():
            joints = joints.index_copy(1, idx, v[p])
        return BodyParams(v["root"], v["transl"], joints, v["expression"], v["shape"].expand(f, -1))

    def set_params(self, params: BodyParams) -> None:
        """Replace the current estimate's pose (root, translation, joints) with ``params``'."""
        self.values["root"] = params.root_orient.detach().clone()
        self.values["transl"] = params.transl.detach().clone()
        for p, idx in self.joint_index.items():
            self.values[p] = params.joints[:, idx].detach().clone()

    def loss(self, stage: FitStage) -> Tensor:
        cfg, t = self.config, self.targets
        params = self.params()
        kp, _ = self.model.posed_keypoints(params)
        cam = to_camera(kp, self.viewmat)
        uv = project_points(cam, self.K)
        residual = (uv - t.keypoints[..., :2]) / self.scale[:, None, None]
        sigma_2d = cfg.sigma_2d * stage.sigma_scale
        # Each group is a robust mean over its own points, so the 16 face points weigh as much as
        # the body's joints when gamma says so. Until hands / face get their own weight, the
        # pose model's coarse hand and face points stand in for them.
        # Frames without a detected face keep the coarse face points when the face group has its
        # own weight: nothing else would turn their heads (a turned head is what the face mesh
        # misses; taiji: 22% of the frames). Not in the body stages, though: the head is not free
        # there, so the body alone follows those guessed points (mmpose's body fit, real_videos_fb).
        coarse = stage.coarse_weight * stage.w_pose
        face_frames = self.face_missing if stage.w_face > 0 else torch.ones_like(self.face_missing)
        fallback = stage.w_face == 0 or "face" in stage.optimize
        groups = (
            (stage.w_pose, self.group_mask["pose"]),
            (coarse * fallback, self.group_mask["pose_face"] * face_frames[:, None]),
            (coarse * (stage.w_hand == 0), self.group_mask["pose_hand"]),
            (stage.w_hand, self.group_mask["hand"]),
            (stage.w_face, self.group_mask["face_rigid" if stage.rigid_face_only else "face"]),
        )
        total = residual.new_zeros(())
        for gamma, mask in groups:
            if gamma > 0:
                total = total + gamma * weighted_gm(residual, mask * self.conf, sigma_2d)

        use_depth = stage.face_z > 0 and t.face_depth is not None
        if (stage.w_face_mesh > 0 or stage.w_openings > 0 or use_depth) and self.face_mesh is not None:
            reg, landmarks = self.face_mesh
            det = t.face_mesh[:, landmarks]
            read = 0.0  # [F, L, 2] what the detector reads beyond the model's points, in pixels
            if self.calibration is not None and (stage.w_face_mesh > 0 or stage.w_openings > 0):
                read = self.calibration.offsets(params.expression, t.face_mesh[:, EYE_CORNERS])
            if stage.w_face_mesh > 0:
                face_cam = to_camera(self.model.posed_points(params, reg), self.viewmat)
                res = (project_points(face_cam, self.K) + read - det[..., :2]) / self.scale[:, None, None]
                total = total + stage.w_face_mesh * weighted_gm(res, det[..., 2], cfg.sigma_2d)
            if stage.w_openings > 0 and self.opening_pairs.numel() > 0:
                # The openings move the face, not the head: a gap's length in the image also
                # changes with the head's pitch (synthetic head rotation error +0.5 degrees).
                face_only = dataclasses.replace(params.detach(), expression=params.expression)
                cam = to_camera(self.model.posed_points(face_only, reg), self.viewmat)
                uv = project_points(cam, self.K) + read
                a, b = self.opening_pairs
                gap = ((uv[:, a] - uv[:, b]) - (det[:, a, :2] - det[:, b, :2])) / self.scale[:, None, None]
                w = det[:, a, 2] * det[:, b, 2]
                total = total + stage.w_openings * weighted_gm(gap, w, cfg.sigma_2d)
            if use_depth:
                # The depths turn the head, not the face: through the expression they pull lips
                # and lids toward MediaPipe's depth guesses (synthetic expression error +10%).
                rigid = dataclasses.replace(params, expression=params.expression.detach())
                face_cam = to_camera(self.model.posed_points(rigid, reg), self.viewmat)
                total = total + stage.face_z * self._face_depth_loss(face_cam, landmarks, det[..., 2])

        if stage.w_silhouette > 0 and self.silhouette is not None:
            reg, sil, spacing = self.silhouette
            body_cam = to_camera(self.model.posed_points(params, reg), self.viewmat)
            uv_body = project_points(body_cam, self.K)
            depth = body_cam[..., 2].detach().mean(1).clamp_min(MIN_DEPTH)
            tolerance = 0.5 * spacing * self.K[:, 0, 0] / depth
            sil_loss = silhouette_loss(uv_body, sil, self.scale, cfg.sigma_2d, tolerance)
            total = total + stage.w_silhouette * sil_loss

        if stage.body_3d > 0 and t.pose_world is not None:
            body = kp[:, : KEYPOINT_GROUPS["pose"].stop]
            hip = 0.5 * (body[:, LEFT_HIP] + body[:, RIGHT_HIP])
            rel = (body - hip[:, None]) @ self.viewmat[:, :3, :3].transpose(1, 2)
            w = t.pose_world[..., 3].clamp(0, 1) * self.group_mask["pose"][:33] * (self.conf[:, :33] > 0)
            total = total + stage.body_3d * weighted_gm(rel - t.pose_world[..., :3], w, cfg.sigma_3d)

        if stage.hand_z > 0 and t.hand_depth is not None:
            for g, offset in (("left_hand", 0), ("right_hand", 21)):
                sl = KEYPOINT_GROUPS[g]
                hand = cam[:, sl]
                wrist_z = hand[:, :1, 2].detach().clamp_min(MIN_DEPTH)
                depth = cfg.hand_depth_scale * t.hand_depth[:, offset : offset + 21]
                target_z = depth * wrist_z / self.K[:, 0, 0, None]
                target = torch.cat([hand[..., :2].detach(), target_z[..., None]], dim=-1)
                total = total + stage.hand_z * z_only_gm(hand, target, self.conf[:, sl], cfg.sigma_z)

        rotvecs = params.joints
        angle = rotvecs.norm(dim=-1).clamp_min(1e-12)  # [F, P]
        total = total + stage.limits * (angle - self.joint_limit).clamp_min(0).square().mean()
        if stage.init_pull > 0:
            total = total + stage.init_pull * (rotvecs - self.init.joints).square().mean()
        if stage.hand_prior > 0 and self.articulation is not None:
            total = total + stage.hand_prior * self.articulation.penalty(rotvecs)
        if stage.body_prior > 0 and self.body_articulation is not None:
            total = total + stage.body_prior * self.body_articulation.penalty(rotvecs)
        if stage.smooth > 0 and t.num_frames > 1:
            smooth = (rotvecs[1:] - rotvecs[:-1]).square().mean()
            smooth = smooth + _rotation_distance(params.root_orient[1:], params.root_orient[:-1]).mean()
            smooth = smooth + cfg.transl_smooth * (params.transl[1:] - params.transl[:-1]).square().mean()
            total = total + stage.smooth * smooth
        if stage.expression_smooth > 0 and t.num_frames > 1:
            step = params.expression[1:] - params.expression[:-1]
            total = total + stage.expression_smooth * step.square().mean()
        total = total + stage.expression_reg * params.expression.square().mean()
        total = total + stage.range_weight * _box(params.expression, self.model.expression_bounds)
        total = total + stage.shape_reg * (self.values["shape"] - self.init.shape[:1]).square().mean()
        total = total + stage.range_weight * _box(self.values["shape"], self.model.shape_bounds)
        # In units of the 2D sigma: a residual of one sigma costs ~1, so L-BFGS's step and
        # curvature estimates start at a sensible scale whatever the image size.
        return total / cfg.sigma_2d**2

    def _face_depth_loss(self, face_cam: Tensor, landmarks: Tensor, conf: Tensor) -> Tensor:
        """Robust error of the face's relative depth pattern against MediaPipe's face-mesh depths
        (converted to metres at the face's depth, scaled by ``face_depth_scale``), each side
        centred on its confidence-weighted mean: only the pattern counts, which fixes the head's
        pitch and yaw where 2D landmarks leave them loose. face_cam: [F, L, 3]; conf: [F, L]."""
        cfg = self.config
        w = conf / conf.sum(1, keepdim=True).clamp_min(1e-8)
        model_z = face_cam[..., 2]
        depth = model_z.detach().mean(1, keepdim=True).clamp_min(MIN_DEPTH)
        target = cfg.face_depth_scale * self.targets.face_depth[:, landmarks] * depth / self.K[:, 0, 0, None]
        res = (model_z - (w * model_z).sum(1, keepdim=True)) - (target - (w * target).sum(1, keepdim=True))
        return weighted_gm(res[..., None], conf, cfg.sigma_face_z)

    def run_stage(self, stage: FitStage, progress: Progress | None) -> tuple[float, float]:
        if stage.body_prior > 0:  # the axes of the shape fitted so far (body_articulation_prior)
            prior = body_articulation_prior(self.model, self.values["shape"])
            self.body_articulation = prior if prior.joints.numel() else None
        moving = [g for g in stage.optimize if self.values[g].numel() > 0]
        for g in self.values:
            self.values[g].requires_grad_(g in moving)
        with torch.no_grad():
            first = float(self.loss(stage))
        if not moving or stage.iterations == 0:
            return first, first
        calls = [0]

        def reported_loss() -> Tensor:
            value = self.loss(stage)
            calls[0] += 1
            if progress is not None:
                progress(ProgressEvent(stage.name, calls[0], stage.iterations, loss=float(value.detach())))
            return value

        tensors = [self.values[g] for g in moving]
        if self.config.bounded_expression and "expression" in moving and self.model.expression_bounds:
            # L-BFGS-B keeps the expression inside the model's range; the rest is free.
            bounds = [self.model.expression_bounds if g == "expression" else None for g in moving]
            minimize_bounded(tensors, bounds, reported_loss, stage.iterations, self.config.history_size)
        else:
            opt = torch.optim.LBFGS(
                tensors,
                lr=1.0,
                max_iter=stage.iterations,
                history_size=self.config.history_size,
                line_search_fn="strong_wolfe",
                tolerance_grad=1e-9,
                tolerance_change=0.0,  # run the stage's iterations: small losses are not converged ones
            )

            def closure():
                opt.zero_grad(set_to_none=False)
                loss = reported_loss()
                loss.backward()
                return loss

            opt.step(closure)
        for g in moving:
            self.values[g].requires_grad_(False)
        with torch.no_grad():
            last = float(self.loss(stage))
        return first, last


def _silhouette_problem(model: BodyModel, masks: Tensor, count: int):
    vertices = silhouette_vertices(model.num_vertices, count).tolist()
    names = [f"outline_{v}" for v in vertices]
    terms = {n: {v: 1.0} for n, v in zip(names, vertices, strict=True)}
    reg = KeypointRegressor(names, terms, {}, model.num_joints)
    with torch.no_grad():
        rest = model(model.default_params(1)).vertices[0, torch.tensor(vertices)]
    spacing = float(mean_neighbour_distance(rest.double(), 1).mean())
    return reg.to(model.device), SilhouetteTargets.from_masks(masks).to(model.device), spacing


def rigid_face_points(model: BodyModel, tolerance: float = 0.003) -> Tensor:
    """[K] bool: the keypoints that no single facial action (at 1) moves by more than
    ``tolerance`` metres in the rest pose (eye corners and the nose, not lips, lids or chin)."""
    e = len(model.expression_names)
    with torch.no_grad():
        params = model.default_params(e + 1)
        params.expression[1:] = torch.eye(e, dtype=params.expression.dtype)
        kp, _ = model.posed_keypoints(params)
        moved = (kp[1:] - kp[:1]).norm(dim=-1).amax(dim=0)
    return (moved < tolerance).cpu()


def _box(x: Tensor, bounds: tuple[float, float] | None) -> Tensor:
    """Squared distance of ``x``'s entries outside [lo, hi], summed (0 without bounds)."""
    if bounds is None:
        return x.new_zeros(())
    lo, hi = bounds
    return (lo - x).clamp_min(0).square().sum() + (x - hi).clamp_min(0).square().sum()


def _rotation_distance(a: Tensor, b: Tensor) -> Tensor:
    """[N] squared Frobenius distance between the rotations of axis-angles a, b [N, 3]."""
    return (axis_angle_to_matrix(a) - axis_angle_to_matrix(b)).square().sum((-1, -2))
