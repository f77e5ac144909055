"""Fitting the body model to a clip's detections: EVA §3.2 (eq. 9-12) on free components.

Objective over all frames at once (batched body model, shape shared by the clip):

    L = L_2D + lambda_bp L_bp + lambda_hp L_hp + priors

- ``L_2D``: Geman-McClure reprojection error of the model keypoints (``body.KEYPOINT_NAMES``:
  MediaPipe's 33 pose + 2 x 21 hand + 16 face points) against the detections, weighted by a
  per-group weight gamma (pose / hand / face, set per stage) and the detection confidence omega.
  Residuals are measured in units of the person's height in the image, so one sigma serves
  every resolution.
- ``L_bp`` (body prior): VPoser is licensed, so its role is played by (a) the robust 3D term
  against MediaPipe's metric pose world landmarks (EVA's J^3D_b guidance), (b) anatomical range
  limits per joint part (a hinge on the rotation angle), (c) a pull toward the initial estimate
  (the official code's stage 1 term), and (d) temporal smoothness across frames.
- ``L_hp`` (hand prior): psi_z, the robust term on relative finger depth only, against
  MediaPipe's hand landmark depth (relative to the wrist, converted to metres at the model's
  wrist depth and scaled by ``hand_depth_scale``: MediaPipe's depths are compressed) -- EVA uses
  HaMeR's 3D hands the same way -- plus an anatomy prior on the finger joints (``hands.
  articulation_prior``: hinges stay hinges, knuckles do not twist, metacarpals barely move).
- Face: the expression coefficients are fitted through the 16 face points and, where the body
  model has a face-mesh correspondence (``face_mesh``), through all of MediaPipe's face-mesh
  landmarks, with a small sparsity prior and the model's valid range (``clip.fit_clip`` then
  smooths it over time). The face mesh's relative depths (``face_z``, MediaPipe's z as the hands'
  psi_z) turn the head: 2D landmarks leave its pitch and yaw loose. Frames where no face was
  found keep the pose model's coarse face points (nose, eyes, ears) in the stages that move the
  head.
- Outline (``align.silhouette``): a two-sided chamfer between the person mask's outline and the
  projected body, in the last, short stage (``outline``), where the targets carry masks.

Optimiser: ``torch.optim.LBFGS`` with strong-Wolfe line search, in stages as in the paper's
appendix: body init (the head's pose from the face points no facial action moves), first with
an 8x wider 2D scale so that joints far outside the robust scale are pulled in; hands with
the hand prior; the expression on its own (inside a joint stage its small gradients barely
move); fine-tune with hands and face emphasised; the same with the outline added. The
initial estimate turns each detected hand's palm to the detected 3D palm (``orient_hands``), so
the fit starts on the right side of the palm-in / palm-out ambiguity, and the hands stage does
it again for the fitted forearms.
Missing detections have confidence 0 and drop out; a frame with nothing detected keeps its
initial estimate, moved only by the smoothness term (``clip.fit_clip`` then fills hands from
neighbouring frames).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import roma
import torch
from torch import Tensor

from eva_engine.align.hands import HandTrackConfig, articulation_prior
from eva_engine.align.robust import weighted_gm, z_only_gm
from eva_engine.align.silhouette import (
    SilhouetteTargets,
    silhouette_loss,
    silhouette_vertices,
)
from eva_engine.body import KEYPOINT_GROUPS, PART_NAMES, BodyModel, BodyParams
from eva_engine.body.kinematics import axis_angle_to_matrix
from eva_engine.geometry import MIN_DEPTH, mean_neighbour_distance, project_points, to_camera
from eva_engine.progress import Progress, ProgressEvent

# Pose landmarks that are body joints (shoulders .. foot index); the others are face points
# and hand points that the face and hand groups measure better.
POSE_BODY = (11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32)
POSE_FACE = tuple(range(11))
POSE_HAND = (17, 18, 19, 20, 21, 22)
LEFT_HIP, RIGHT_HIP = 23, 24
# Rotation-angle limits (radians) of one joint, per part: generous ranges that rule out
# impossible twists (a finger bent 150 degrees, a head turned backwards) but no real pose.
JOINT_LIMITS = {"body": 2.4, "hand": 1.75, "face": 0.9}
PARAM_GROUPS = ("root", "transl", "body", "hand", "face", "expression", "shape")


@dataclass
class FitTargets:
    """What the fit is matched to, for F frames.

    keypoints:  [F, K, 3] detections (x px, y px, confidence); non-finite entries are dropped.
    K:          [F, 3, 3] or [3, 3] intrinsics; viewmat: [F, 4, 4] or [4, 4] world->camera.
    hand_depth: [F, 42] MediaPipe hand-landmark depth relative to the wrist, in pixels, or None.
    pose_world: [F, 33, 4] MediaPipe metric pose world landmarks + visibility, or None.
    face_mesh:  [F, 478, 3] MediaPipe face-mesh landmarks (x px, y px, confidence), or None.
    person_masks: [F, H, W] person masks in [0, 1] (the silhouette term, ``align.silhouette``),
                or None; a frame without a mask is all ones (it then contributes nothing).
    face_depth: [F, L] MediaPipe face-mesh landmark depth relative to their mean, in pixels, or
                None (weighted by ``face_mesh``'s confidence).
    """

    keypoints: Tensor
    K: Tensor
    viewmat: Tensor
    hand_depth: Tensor | None = None
    pose_world: Tensor | None = None
    face_mesh: Tensor | None = None
    person_masks: Tensor | None = None
    face_depth: Tensor | None = None

    def __post_init__(self) -> None:
        kp = torch.as_tensor(self.keypoints, dtype=torch.float32)
        if kp.ndim != 3 or kp.shape[-1] != 3:
            raise ValueError(f"keypoints must be [F, K, 3], got {tuple(kp.shape)}")
        f = kp.shape[0]
        ok = torch.isfinite(kp).all(-1) & (kp[..., 2] > 0)
        conf = torch.where(ok, kp[..., 2].clamp(0.0, 1.0), torch.zeros_like(kp[..., 2]))
        xy = torch.where(ok[..., None], kp[..., :2], torch.zeros_like(kp[..., :2]))
        self.keypoints = torch.cat([xy, conf[..., None]], dim=-1)
        self.K = torch.as_tensor(self.K, dtype=torch.float32)
        self.viewmat = torch.as_tensor(self.viewmat, dtype=torch.float32)
        if self.K.shape not in ((3, 3), (f, 3, 3)) or self.viewmat.shape not in ((4, 4), (f, 4, 4)):
            raise ValueError(
                f"K must be [3, 3] or [{f}, 3, 3] and viewmat [4, 4] or [{f}, 4, 4], got "
                f"{tuple(self.K.shape)} and {tuple(self.viewmat.shape)}"
            )
        if self.hand_depth is not None:
            hd = torch.as_tensor(self.hand_depth, dtype=torch.float32)
            if hd.shape != (f, 42):
                raise ValueError(f"hand_depth must be [{f}, 42], got {tuple(hd.shape)}")
            self.hand_depth = torch.nan_to_num(hd, nan=0.0, posinf=0.0, neginf=0.0)
        if self.pose_world is not None:
            pw = torch.as_tensor(self.pose_world, dtype=torch.float32)
            if pw.shape != (f, 33, 4):
                raise ValueError(f"pose_world must be [{f}, 33, 4], got {tuple(pw.shape)}")
            bad = ~torch.isfinite(pw).all(-1)
            pw = torch.where(bad[..., None], torch.zeros_like(pw), pw)
            self.pose_world = pw
        if self.face_mesh is not None:
            fm = torch.as_tensor(self.face_mesh, dtype=torch.float32)
            if fm.ndim != 3 or fm.shape[0] != f or fm.shape[2] != 3:
                raise ValueError(f"face_mesh must be [{f}, L, 3], got {tuple(fm.shape)}")
            ok = torch.isfinite(fm).all(-1) & (fm[..., 2] > 0)
            self.face_mesh = torch.where(ok[..., None], fm, torch.zeros_like(fm))
        if self.person_masks is not None:
            pm = torch.as_tensor(self.person_masks, dtype=torch.float32)
            if pm.ndim != 3 or pm.shape[0] != f:
                raise ValueError(f"person_masks must be [{f}, H, W], got {tuple(pm.shape)}")
            self.person_masks = torch.nan_to_num(pm, nan=1.0).clamp(0.0, 1.0)
        if self.face_depth is not None:
            fd = torch.as_tensor(self.face_depth, dtype=torch.float32)
            if self.face_mesh is None or fd.shape != self.face_mesh.shape[:2]:
                shape = tuple(fd.shape)
                raise ValueError(f"face_depth must be [F, L] beside face_mesh [F, L, 3], got {shape}")
            self.face_depth = torch.nan_to_num(fd, nan=0.0, posinf=0.0, neginf=0.0)

    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    def frame_K(self) -> Tensor:
        """[F, 3, 3]."""
        return self.K.expand(self.num_frames, 3, 3) if self.K.ndim == 2 else self.K

    def frame_viewmat(self) -> Tensor:
        """[F, 4, 4]."""
        return self.viewmat.expand(self.num_frames, 4, 4) if self.viewmat.ndim == 2 else self.viewmat

    def person_scale(self) -> Tensor:
        """[F] person size in pixels, the unit of the 2D residuals: the diagonal of the confident
        pose points' box (the clip's median where a frame has too few), kept between 5% and 100%
        of the image diagonal (a close-up's off-image legs must not shrink the residuals)."""
        kp = self.keypoints[:, KEYPOINT_GROUPS["pose"]]
        ok = kp[..., 2] > 0.3
        big = torch.tensor(1e9)
        lo = torch.where(ok[..., None], kp[..., :2], big).amin(1)
        hi = torch.where(ok[..., None], kp[..., :2], -big).amax(1)
        diag = (hi - lo).norm(dim=-1)
        valid = ok.sum(1) >= 4
        image_diag = 2.0 * self.frame_K()[:, :2, 2].norm(dim=-1)  # principal point ~ image centre
        fallback = diag[valid].median() if valid.any() else image_diag
        return torch.minimum(torch.maximum(torch.where(valid, diag, fallback), 0.05 * image_diag), image_diag)


@dataclass(frozen=True)
class FitStage:
    """One L-BFGS stage: which parameter groups move and the weight of every term."""

    name: str
    iterations: int
    optimize: tuple[str, ...]
    w_pose: float = 1.0
    w_hand: float = 0.0
    w_face: float = 0.0
    coarse_weight: float = 0.3
    """Weight (relative to ``w_pose``) of the pose model's coarse hand and face points while this
    stage gives the hand or face group no weight of its own (``w_hand`` or ``w_face`` 0); the face
    points also in the frames where no face was detected, in stages that move the face part."""
    rigid_face_only: bool = False
    """Use only the face points that no facial action moves (eye corners, nose): the head's pose
    is fitted before the expression, so the mouth's points must not turn the head."""
    w_face_mesh: float = 0.0
    w_openings: float = 0.0
    """Weight of the eye and mouth openings: the face mesh's lid and inner-lip landmark pairs
    (``face_mesh.OPENING_PAIRS``), compared as differences. Among the correspondence's 411
    landmarks the 22 that open and close the face weigh little, and an offset between the
    person's landmarks and the model's moves both points of a pair alike, so the difference
    isolates the opening."""
    face_z: float = 0.0
    """Weight of the face mesh's relative-depth term (``face_depth``), where the targets have it."""
    w_silhouette: float = 0.0
    """Weight of the silhouette terms (``align.silhouette``), where the targets have person masks."""
    body_3d: float = 0.0
    hand_z: float = 0.0
    init_pull: float = 0.0
    hand_prior: float = 0.0
    smooth: float = 0.1
    limits: float = 1.0
    range_weight: float = 10.0
    """Weight of the quadratic penalty outside a parameter's valid range (expression, shape), as
    ``limits`` is the joints'."""
    expression_reg: float = 0.0
    expression_smooth: float = 0.0
    """Weight of the frame-to-frame expression change (off by default: it slows L-BFGS down
    across the coupled frames; ``clip.fit_clip`` smooths the expression over time instead)."""
    shape_reg: float = 1e-3
    sigma_scale: float = 1.0
    """Multiplier of the 2D Geman-McClure scale (``FitConfig.sigma_2d``) in this stage."""
    orient_hands_first: bool = False
    """Before this stage, turn each detected hand's wrist to the detected palm again
    (``orient_hands``, if ``FitConfig.orient_hands``): the body stages twist the forearms, and a
    hand turned for the initial estimate's forearm turns with them."""

    def __post_init__(self) -> None:
        unknown = set(self.optimize) - set(PARAM_GROUPS)
        if unknown:
            raise ValueError(f"unknown parameter groups {sorted(unknown)}; valid: {PARAM_GROUPS}")
        if self.iterations < 0:
            raise ValueError("iterations must be >= 0")


def default_stages() -> tuple[FitStage, ...]:
    """The paper's three stages (appendix: body init; hands; fine-tune with hands and face
    emphasised), with the face's expression fitted in a stage of its own before the fine-tune.
    The body and fine-tune stages run 120 L-BFGS iterations: one step length serves every frame
    of the clip, so the joint problem converges slower than one frame would (``docs/alignment.md``
    has the measurements).

    The last stage (``outline``) is the fine-tune again, 30 iterations, with the person mask's
    outline (``align.silhouette``; its 2,500 body points cost more per step than every other
    term): keypoints fix the joints, not the shoulders' or the cranium's outline around them.

    The body stage runs first with an 8x wider Geman-McClure scale (``body_coarse``): where
    MediaPipe's 3D world landmarks put an arm elsewhere than its 2D points do, the initial
    estimate's arm lies several sigmas from the detections, where the robust term's gradient has
    vanished, and the narrow-scale fit keeps it there (taiji: 6% of the frames with a joint more
    than 0.2 person heights off, ``bench/results/align_before.md``; 0% after). The wide scale pulls
    it in; the stages after it are robust again.
    """
    body = FitStage(
        "body",
        120,
        ("root", "transl", "body", "shape"),
        w_face=0.3,
        rigid_face_only=True,
        body_3d=1.0,
        init_pull=0.05,
    )
    refine = FitStage(
        "refine",
        120,
        PARAM_GROUPS,
        w_hand=2.0,
        w_face=2.0,
        w_face_mesh=2.0,
        w_openings=30.0,
        face_z=10.0,
        body_3d=0.3,
        hand_z=0.5,
        hand_prior=1.0,
        init_pull=0.01,
        expression_reg=1e-3,
    )
    return (
        dataclasses.replace(body, name="body_coarse", iterations=60, sigma_scale=8.0),
        body,
        FitStage(
            "hands",
            40,
            ("hand",),
            w_hand=1.0,
            hand_z=1.0,
            hand_prior=1.0,
            smooth=0.05,
            orient_hands_first=True,
        ),
        # Expression on its own: inside the joint refine stage its small gradients barely move.
        # No range penalty here: from the neutral face (every coefficient at its bound, 0) the
        # first step takes half the coefficients below 0, where the penalty's curvature dwarfs
        # the face points' and L-BFGS stalls at the bound (expression error 5.21 mm against the
        # neutral face's 5.26, bench/results/align_before.md). The refine stage's penalty and
        # the final clamp bring the coefficients back into range.
        FitStage(
            "face",
            40,
            ("face", "expression"),
            w_pose=0.0,
            w_face=2.0,
            w_face_mesh=2.0,
            w_openings=30.0,
            face_z=10.0,
            smooth=0.05,
            expression_reg=1e-3,
            range_weight=0.0,
        ),
        refine,
        # The outline last and short: its body points cost more per step than all the rest.
        dataclasses.replace(refine, name="outline", iterations=30, w_silhouette=3.0),
    )


@dataclass(frozen=True)
class FitConfig:
    """Fitting settings. Sigmas are the Geman-McClure scales: 2D in person heights, 3D and z in
    metres."""

    stages: tuple[FitStage, ...] = field(default_factory=default_stages)
    hands: HandTrackConfig = field(default_factory=HandTrackConfig)
    ik_iterations: int = 40
    sigma_2d: float = 0.1
    sigma_3d: float = 0.1
    sigma_z: float = 0.03
    expression_sigma: float = 0.04
    """Seconds: the Gaussian that smooths the fitted expression over time (``clip.fit_clip``)."""
    transl_smooth: float = 10.0
    """Weight of frame-to-frame translation (m²) against rotation (rad²) in the smoothness term:
    10 puts 1 cm of jitter on a par with ~1.8 degrees."""
    dense_face: bool = True
    """Fit the face to all of MediaPipe's face-mesh landmarks through the body model's
    correspondence (``align.face_mesh``), where the model has one."""
    hand_depth_scale: float = 1.6
    """MediaPipe's relative hand depths are compressed: on rendered Anny hands (``bench/align.py``)
    the true depths are 1.6-1.7 x its values (correlation 0.8); they are scaled by this."""
    face_depth_scale: float = 0.9
    """MediaPipe's face-mesh depths are not: on rendered Anny faces the true relative depths are
    0.9 x its values (correlation 0.95, ``bench/align.py``'s synthetic clip)."""
    sigma_face_z: float = 0.01
    """Metres: the Geman-McClure scale of the face's relative depths (they span about +-2 cm)."""
    orient_hands: bool = True
    """Start each detected hand's wrist rotation at the rotation that best aligns the model's palm
    with the detected 3D palm (Kabsch), instead of the rest pose: the fit then starts on the right
    side of the palm-facing / back-facing ambiguity."""
    silhouette_points: int = 2500
    """How many of the body model's vertices stand for its outline in the silhouette terms."""
    history_size: int = 20


@dataclass
class FitResult:
    """params: the fitted clip; stage_losses: (first, last) objective per stage; seconds."""

    params: BodyParams
    stage_losses: dict[str, tuple[float, float]]
    seconds: float


class _Problem:
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
        self.group_mask = {
            "pose": _mask(kp.shape[1], POSE_BODY),
            "pose_face": _mask(kp.shape[1], POSE_FACE),
            "pose_hand": _mask(kp.shape[1], POSE_HAND),
            "hand": _mask(
                kp.shape[1], range(KEYPOINT_GROUPS["left_hand"].start, KEYPOINT_GROUPS["right_hand"].stop)
            ),
            "face": _mask(kp.shape[1], range(KEYPOINT_GROUPS["face"].start, KEYPOINT_GROUPS["face"].stop)),
        }
        self.group_mask["face_rigid"] = self.group_mask["face"] * rigid_face_points(model).float()
        self.face_missing = ((self.conf * self.group_mask["face"]).sum(1) == 0).float()  # [F]
        limits = torch.tensor([JOINT_LIMITS[p] for p in PART_NAMES])
        self.joint_limit = limits[part]  # [P]
        uses_prior = any(s.hand_prior > 0 for s in config.stages)
        self.articulation = articulation_prior(model) if uses_prior else None
        self.face_mesh = None  # (regressor, landmark indices) of the dense face term
        self.opening_pairs = None  # [2, Q] positions in those landmark indices
        dense = config.dense_face and targets.face_mesh is not None
        if dense and any(s.w_face_mesh > 0 or s.w_openings > 0 or s.face_z > 0 for s in config.stages):
            from eva_engine.align.face_mesh import OPENING_PAIRS, load_correspondence

            corr = load_correspondence(model)
            if corr is not None:
                self.face_mesh = corr.regressor(model)
                at = {int(k): i for i, k in enumerate(self.face_mesh[1])}
                pairs = [(at[a], at[b]) for a, b in OPENING_PAIRS if a in at and b in at]
                self.opening_pairs = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2).T
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
            if stage.w_face_mesh > 0:
                face_cam = to_camera(self.model.posed_points(params, reg), self.viewmat)
                res = (project_points(face_cam, self.K) - det[..., :2]) / self.scale[:, None, None]
                total = total + stage.w_face_mesh * weighted_gm(res, det[..., 2], cfg.sigma_2d)
            if stage.w_openings > 0 and self.opening_pairs.numel() > 0:
                # The openings move the face, not the head: a gap's length in the image also
                # changes with the head's pitch (synthetic head rotation error +0.5 degrees).
                face_only = dataclasses.replace(params.detach(), expression=params.expression)
                cam = to_camera(self.model.posed_points(face_only, reg), self.viewmat)
                uv = project_points(cam, self.K)
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
            a = self.articulation
            off_axis = (a.projectors @ rotvecs[:, a.joints, :, None]).squeeze(-1)  # [F, M, 3]
            total = total + stage.hand_prior * (a.weights * off_axis.square().sum(-1)).mean()
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
        moving = [g for g in stage.optimize if self.values[g].numel() > 0]
        for g in self.values:
            self.values[g].requires_grad_(g in moving)
        with torch.no_grad():
            first = float(self.loss(stage))
        if not moving or stage.iterations == 0:
            return first, first
        opt = torch.optim.LBFGS(
            [self.values[g] for g in moving],
            lr=1.0,
            max_iter=stage.iterations,
            history_size=self.config.history_size,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-9,
            tolerance_change=0.0,  # run the stage's iterations: small losses are not converged ones
        )
        calls = [0]

        def closure():
            opt.zero_grad(set_to_none=False)
            loss = self.loss(stage)
            loss.backward()
            calls[0] += 1
            if progress is not None:
                progress(ProgressEvent(stage.name, calls[0], stage.iterations, loss=float(loss)))
            return loss

        opt.step(closure)
        for g in moving:
            self.values[g].requires_grad_(False)
        with torch.no_grad():
            last = float(self.loss(stage))
        return first, last


def _silhouette_problem(model: BodyModel, masks: Tensor, count: int):
    from eva_engine.body.keypoints import KeypointRegressor

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


def _mask(n: int, indices) -> Tensor:
    m = torch.zeros(n)
    m[list(indices)] = 1.0
    return m


def _box(x: Tensor, bounds: tuple[float, float] | None) -> Tensor:
    """Squared distance of ``x``'s entries outside [lo, hi], summed (0 without bounds)."""
    if bounds is None:
        return x.new_zeros(())
    lo, hi = bounds
    return (lo - x).clamp_min(0).square().sum() + (x - hi).clamp_min(0).square().sum()


def _rotation_distance(a: Tensor, b: Tensor) -> Tensor:
    """[N] squared Frobenius distance between the rotations of axis-angles a, b [N, 3]."""
    return (axis_angle_to_matrix(a) - axis_angle_to_matrix(b)).square().sum((-1, -2))


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
        w = det[..., 2] * _mask(33, POSE_BODY + POSE_FACE)
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
        problem = _Problem(model, targets, config, params)
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
    from eva_engine.align.hands import SIDES, hand_root_joints

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


def fit_sequence(
    model: BodyModel,
    targets: FitTargets,
    init: BodyParams | None = None,
    config: FitConfig | None = None,
    progress: Progress | None = None,
) -> FitResult:
    """Fit ``model`` to a clip. ``init``: a starting estimate (e.g. a previous fit, or an
    estimator's output); by default :func:`initial_estimate`. Returns the fitted parameters with
    expression and shape inside the model's valid ranges. ``progress`` hears every loss
    evaluation (stage: the ``FitStage``'s name; done of its iterations; the loss)."""
    config = config or FitConfig()
    started = time.perf_counter()
    if init is None:
        init = initial_estimate(model, targets, config)
    if init.batch_size != targets.num_frames:
        raise ValueError(f"init has {init.batch_size} frames, targets {targets.num_frames}")
    problem = _Problem(model, targets, config, init)
    losses = {}
    for stage in config.stages:
        if stage.orient_hands_first and config.orient_hands and targets.hand_depth is not None:
            problem.set_params(orient_hands(model, problem.params(), targets, config.hand_depth_scale))
        losses[stage.name] = problem.run_stage(stage, progress)
    params = problem.params().map(lambda t: t.detach().clone())
    for name, bounds in (("expression", model.expression_bounds), ("shape", model.shape_bounds)):
        if bounds is not None:
            getattr(params, name).clamp_(*bounds)
    if not all(torch.isfinite(t).all() for t in params.tensors().values()):
        raise FloatingPointError("fitting produced non-finite parameters")  # a bug, never data
    return FitResult(params=params, stage_losses=losses, seconds=time.perf_counter() - started)


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
