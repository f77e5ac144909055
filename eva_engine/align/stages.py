"""The fit's settings: its L-BFGS stages (``FitStage``, ``default_stages``) and the rest of
``FitConfig``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from eva_engine.align.hands import HandTrackConfig

PARAM_GROUPS = ("root", "transl", "body", "hand", "face", "expression", "shape")


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
    body_prior: float = 0.0
    """Weight of the body's articulation prior (``align.body_prior``): the arms' second bones
    twist only, the elbow is a hinge, the clavicle, shoulder, spine and neck bones move little.
    Off in every default stage: it steadies the synthetic close-up's skin, and real people's
    shoulders and necks move where it holds them (``docs/alignment.md``, "The body's redundant
    bones")."""
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
    # The face's terms, one set for every stage that moves the expression (face, refine, outline).
    face_terms = dict(w_face=2.0, w_face_mesh=2.0, w_openings=30.0, face_z=10.0, expression_reg=1e-3)
    refine = FitStage(
        "refine",
        120,
        PARAM_GROUPS,
        w_hand=2.0,
        body_3d=0.3,
        hand_z=0.5,
        hand_prior=1.0,
        init_pull=0.01,
        **face_terms,
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
        # No range penalty here: L-BFGS-B keeps the range (FitConfig.bounded_expression). Without
        # it, a penalty stalls torch's L-BFGS at the bound from the neutral face (every
        # coefficient at its bound, 0; expression error 5.21 mm against the neutral face's 5.26,
        # bench/results/align_before.md), so this stage ran unbounded and the refine stage's
        # penalty and the final clamp brought the coefficients back. 200 iterations: one step length
        # serves every frame's expression, and at 40 the fit was far from its optimum (with the
        # detector's calibration, synthetic expression error 3.11 mm at 40, 2.77 at 200;
        # bench/results/expressions/calibration/).
        FitStage(
            "face", 200, ("face", "expression"), w_pose=0.0, smooth=0.05, range_weight=0.0, **face_terms
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
    expression_sigma: float = 0.0
    """Seconds: the Gaussian that smooths the fitted expression over time (``clip.fit_clip``; 0:
    none). Off: at a video's own frame rate, 0.04 s flattened blinks and cut the rendered mouth's
    range by a sixth (``docs/alignment.md``, "The expression's time smoothing")."""
    transl_smooth: float = 10.0
    """Weight of frame-to-frame translation (m²) against rotation (rad²) in the smoothness term:
    10 puts 1 cm of jitter on a par with ~1.8 degrees."""
    dense_face: bool = True
    """Fit the face to all of MediaPipe's face-mesh landmarks through the body model's
    correspondence (``align.face_mesh``), where the model has one."""
    detector_calibration: bool = True
    """Compare the detections with what MediaPipe reads of the model's face under its expression
    (``align.face_calibration``), not with the correspondence's surface points alone."""
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
    bounded_expression: bool = True
    """Stages that move the expression keep it inside the body model's range (``BodyModel.
    expression_bounds``) by L-BFGS-B (``align.bounded_lbfgs``) instead of torch's L-BFGS with the
    range penalty (``FitStage.range_weight``) and a clamp at the end. Left free, the face stage
    put half of a clip's coefficients below 0 and stopped early, and the refine stage started
    thousands of times above its optimum and spent its steps pulling them back: on the gesturing
    clip the fitted eye range was 0.57 of the detector's (``docs/alignment.md``, "The expression
    kept in its range")."""
    history_size: int = 20
