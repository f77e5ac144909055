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
  (the official code's stage 1 term), and (d) temporal smoothness across frames. An
  articulation prior of the body's redundant bones (``body_prior``: the arms' second bones only
  twist, the elbow is a hinge, clavicle, shoulder, spine and neck bones move little) is an
  option, off by default (``FitStage.body_prior``).
- ``L_hp`` (hand prior): psi_z, the robust term on relative finger depth only, against
  MediaPipe's hand landmark depth (relative to the wrist, converted to metres at the model's
  wrist depth and scaled by ``hand_depth_scale``: MediaPipe's depths are compressed) -- EVA uses
  HaMeR's 3D hands the same way -- plus an anatomy prior on the finger joints (``hands.
  articulation_prior``: hinges stay hinges, knuckles do not twist, metacarpals barely move).
- Face: the expression coefficients are fitted through the 16 face points and, where the body
  model has a face-mesh correspondence (``face_mesh``), through all of MediaPipe's face-mesh
  landmarks, with a small sparsity prior, inside the model's valid range; the landmarks are
  compared with what the detector would read of the model's face (``face_calibration``: the projected
  points plus an offset linear in the expression). The face mesh's relative depths (``face_z``,
  MediaPipe's z as the hands' psi_z) turn the head: 2D landmarks leave its pitch and yaw loose.
  Frames where no face was found keep the pose model's coarse face points (nose, eyes, ears) in
  the stages that move the head.
- Outline (``align.silhouette``): a two-sided chamfer between the person mask's outline and the
  projected body, in the last, short stage (``outline``), where the targets carry masks.

Optimiser: ``torch.optim.LBFGS`` with strong-Wolfe line search; the stages that move the
expression run L-BFGS-B instead (``bounded_lbfgs``, scipy's: the same memory, a line search that
keeps the strong Wolfe conditions), with the expression's range as bounds
(``FitConfig.bounded_expression``). In stages as in the paper's appendix: body init (the head's
pose from the face points no facial action moves), first with an 8x wider 2D scale so that
joints far outside the robust scale are pulled in; hands with the hand prior; the expression on
its own (inside a joint stage its small gradients barely move); fine-tune with hands and face
emphasised; the same with the outline added. The initial estimate turns each detected hand's
palm to the detected 3D palm (``orient_hands``), so the fit starts on the right side of the
palm-in / palm-out ambiguity, and the hands stage does it again for the fitted forearms.
Missing detections have confidence 0 and drop out; a frame with nothing detected keeps its
initial estimate, moved only by the smoothness term (``clip.fit_clip`` then fills hands from
neighbouring frames).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from eva_engine.align.initial import initial_estimate, orient_hands
from eva_engine.align.objective import FitProblem
from eva_engine.align.stages import FitConfig
from eva_engine.align.targets import FitTargets
from eva_engine.body import BodyModel, BodyParams
from eva_engine.progress import Progress


@dataclass
class FitResult:
    """params: the fitted clip; stage_losses: (first, last) objective per stage; seconds."""

    params: BodyParams
    stage_losses: dict[str, tuple[float, float]]
    seconds: float


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
    problem = FitProblem(model, targets, config, init)
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
