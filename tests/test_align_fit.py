"""Body-model alignment on clips with known parameters: the fit recovers them, robustly."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from eva_engine.align.evaluate import expression_error, mpjpe, targets_from_params
from eva_engine.align.fit import fit_sequence
from eva_engine.align.initial import initial_estimate, solve_translation
from eva_engine.align.reprojection import reprojection_error
from eva_engine.align.stages import FitConfig, default_stages
from eva_engine.align.targets import FitTargets
from eva_engine.body import KEYPOINT_GROUPS, PART_NAMES
from eva_engine.geometry import project_points, to_camera
from eva_engine.render import intrinsics, orbit_camera

FRAMES = 6
K = intrinsics(256, 256, 40.0)
VIEW = orbit_camera(0.0, 0.0, 3.0)


def fast_config(scale: float = 0.5) -> FitConfig:
    stages = tuple(
        dataclasses.replace(s, iterations=max(1, int(s.iterations * scale))) for s in default_stages()
    )
    return FitConfig(stages=stages, ik_iterations=20)


@pytest.fixture(scope="module")
def clip(anny_model):
    """Sign-language-like poses: arms raised, fingers bent, a little expression."""
    g = torch.Generator().manual_seed(3)
    truth = anny_model.default_params(FRAMES)
    names = anny_model.pose_joint_names
    part = anny_model.joint_part_ids[1:]
    truth.joints.copy_(torch.randn(truth.joints.shape, generator=g) * 0.08)
    hand = part == 1
    truth.joints[:, hand, 2] += torch.rand(FRAMES, int(hand.sum()), generator=g) * 0.6  # curl
    for side, sign in (("L", 1.0), ("R", -1.0)):
        truth.joints[:, names.index(f"upperarm01.{side}"), 2] += sign * (
            0.3 + 0.6 * torch.rand(FRAMES, generator=g)
        )
        truth.joints[:, names.index(f"lowerarm01.{side}"), 1] += sign * 0.8
    truth.expression[:, anny_model.expression_names.index("jawOpen")] = 0.4
    return truth


def perturbed(truth, seed=1, amount=0.15):
    g = torch.Generator().manual_seed(seed)
    p = truth.map(lambda t: t.clone())
    p.joints.add_(torch.randn(p.joints.shape, generator=g) * amount)
    p.root_orient.add_(torch.randn(p.root_orient.shape, generator=g) * amount)
    p.transl.add_(torch.randn(p.transl.shape, generator=g) * 0.05)
    p.expression.zero_()
    return p


def test_fit_from_perturbed_parameters_recovers_them(anny_model, clip):
    targets = targets_from_params(anny_model, clip, K, VIEW)
    start = perturbed(clip)
    before_2d = reprojection_error(anny_model, start, targets)
    before_3d = mpjpe(anny_model, start, clip)
    result = fit_sequence(anny_model, targets, init=start, config=fast_config())
    after_2d = reprojection_error(anny_model, result.params, targets)
    after_3d = mpjpe(anny_model, result.params, clip)
    for group in ("body", "hands", "face"):
        assert after_2d[group] < 0.5 * before_2d[group], (group, before_2d, after_2d)
    assert after_2d["hands"] < 3.0  # pixels, on a 256 px frame
    assert after_3d["body"] < 0.6 * before_3d["body"] and after_3d["hands"] < 0.6 * before_3d["hands"]
    for first, last in result.stage_losses.values():
        assert last <= first + 1e-7
    assert result.params.expression.min() >= 0 and result.params.expression.max() <= 1


def test_rotation_aligned_hand_error_ignores_only_the_hands_orientation(anny_model, clip):
    """A hand turned about its wrist has hand MPJPE but no rotation-aligned error; bent fingers
    keep theirs."""
    hand = anny_model.joint_part_ids[1:].cpu() == PART_NAMES.index("hand")
    wrists = [i - 1 for i, name in enumerate(anny_model.joint_names) if name in ("wrist.L", "wrist.R")]
    turned = clip.map(lambda t: t.clone())
    turned.joints[:, wrists] += torch.tensor([0.0, 0.6, 0.3])
    err = mpjpe(anny_model, turned, clip)
    assert err["hands"] > 10.0 and err["hands_rotation_aligned"] < 0.1, err
    bent = clip.map(lambda t: t.clone())
    bent.joints[:, hand & ~torch.isin(torch.arange(hand.numel()), torch.tensor(wrists))] += 0.3
    err = mpjpe(anny_model, bent, clip)
    assert err["hands_rotation_aligned"] > 5.0, err


def test_expression_is_fitted_to_the_face_points(anny_model, clip):
    # Waist-up framing (as the wild preset): the jaw moves the chin by ~8 px here.
    view = orbit_camera(0.0, 0.0, 1.2, target=(0.0, 0.5, 0.0))
    targets = targets_from_params(anny_model, clip, K, view, image_size=(256, 256))
    assert targets.keypoints[:, 25:29, 2].eq(0).all()  # knees and ankles are off the image
    start = clip.map(lambda t: t.clone())
    start.expression.zero_()
    face_stage = next(s for s in default_stages() if s.name == "face")
    face_only = FitConfig(stages=(dataclasses.replace(face_stage, optimize=("expression",), iterations=30),))
    result = fit_sequence(anny_model, targets, init=start, config=face_only)

    def worst_face_error(params):
        kp, _ = anny_model.posed_keypoints(params)
        uv = project_points(to_camera(kp, view), K)
        face = KEYPOINT_GROUPS["face"]
        return (uv[:, face] - targets.keypoints[:, face, :2]).norm(dim=-1).max()

    assert worst_face_error(result.params) < 0.25 * worst_face_error(start)
    # 52 coefficients for 16 points are not all identifiable, but the jaw is what moved them.
    jaw = anny_model.expression_names.index("jawOpen")
    assert result.params.expression[:, jaw].mean() > 0.25
    assert result.params.expression.min() >= 0 and result.params.expression.max() <= 1


def test_a_mixed_expression_is_fitted_from_the_neutral_face(anny_model, clip):
    # Several facial actions at once, from the neutral face: every coefficient starts at its
    # bound (0), and a range penalty in the face stage used to stall L-BFGS there.
    view = orbit_camera(0.0, 0.0, 1.2, target=(0.0, 0.5, 0.0))
    truth = clip.map(lambda t: t.clone())
    names = anny_model.expression_names
    for name, value in {
        "jawOpen": 0.3,
        "mouthSmileLeft": 0.6,
        "mouthSmileRight": 0.6,
        "eyeBlinkLeft": 0.8,
        "browInnerUp": 0.7,
        "mouthFunnel": 0.4,
    }.items():
        truth.expression[:, names.index(name)] = value
    targets = targets_from_params(anny_model, truth, K, view, image_size=(256, 256))
    start = truth.map(lambda t: t.clone())
    start.expression.zero_()
    face_stage = next(s for s in default_stages() if s.name == "face")
    result = fit_sequence(anny_model, targets, init=start, config=FitConfig(stages=(face_stage,)))
    before, after = (
        expression_error(anny_model, start, truth),
        expression_error(anny_model, result.params, truth),
    )
    assert after < 0.6 * before, (before, after)
    assert result.params.expression.min() >= 0 and result.params.expression.max() <= 1


def test_initial_estimate_from_detections_alone_and_fit_lowers_hand_error(anny_model, clip):
    targets = targets_from_params(anny_model, clip, K, VIEW)
    init = initial_estimate(anny_model, targets, fast_config())
    # Facing the camera, in front of it, near the true distance.
    assert (init.transl[:, 2] - clip.transl[:, 2]).abs().max() < 0.5
    before = reprojection_error(anny_model, init, targets)
    result = fit_sequence(anny_model, targets, init=init, config=fast_config())
    after = reprojection_error(anny_model, result.params, targets)
    assert after["hands"] < 0.5 * before["hands"]  # the hand stages at least halve the hands' 2D error
    assert after["body"] < before["body"]


def test_translation_solve_is_exact_without_noise(anny_model, clip):
    targets = targets_from_params(anny_model, clip, K, VIEW)
    t = solve_translation(anny_model, clip, targets)
    assert torch.allclose(t, clip.transl, atol=1e-3)


def test_missing_detections_occlusion_and_empty_frames_stay_finite(anny_model, clip):
    targets = targets_from_params(anny_model, clip, K, VIEW)
    kp = targets.keypoints.clone()
    kp[0, KEYPOINT_GROUPS["right_hand"], 2] = 0.0  # hand not found
    kp[1, :, 2] = 0.0  # no person in this frame
    kp[2, :20] = float("nan")  # garbage from a detector
    kp[3, 40:60, :2] = torch.tensor([1e6, -1e6])  # wild outliers, full confidence
    hand_depth = targets.hand_depth.clone()
    hand_depth[4] = float("inf")
    bad = FitTargets(kp, K, VIEW, hand_depth, targets.pose_world)
    assert bad.keypoints[2, :20, 2].eq(0).all()
    start = perturbed(clip, seed=2)
    result = fit_sequence(anny_model, bad, init=start, config=fast_config(0.3))
    for name, t in result.params.tensors().items():
        assert torch.isfinite(t).all(), name

    # The empty frame is pulled toward its neighbours by the smoothness term alone.
    def gap(p):
        return (p.joints[1] - 0.5 * (p.joints[0] + p.joints[2])).norm()

    assert gap(result.params) < gap(start)
    assert (result.params.joints[1] - start.joints[1]).abs().max() < 1.0
    # A clip where nothing at all was detected: finite and facing the camera.
    empty = FitTargets(torch.zeros(2, kp.shape[1], 3), K, VIEW)
    out = fit_sequence(anny_model, empty, config=fast_config(0.2))
    assert all(torch.isfinite(t).all() for t in out.params.tensors().values())


def test_points_behind_the_camera_give_finite_gradients(anny_model, clip):
    targets = targets_from_params(anny_model, clip, K, VIEW)
    start = clip.map(lambda t: t.clone())
    start.transl[:, 2] = 5.0  # the body is behind the camera (which sits at z = 3 looking at -z)
    result = fit_sequence(anny_model, targets, init=start, config=fast_config(0.2))
    assert all(torch.isfinite(t).all() for t in result.params.tensors().values())


def test_targets_validate_shapes():
    with pytest.raises(ValueError, match="keypoints"):
        FitTargets(torch.zeros(3, 91), K, VIEW)
    with pytest.raises(ValueError, match="hand_depth"):
        FitTargets(torch.zeros(3, 91, 3), K, VIEW, hand_depth=torch.zeros(2, 42))
    with pytest.raises(ValueError, match="K must be"):
        FitTargets(torch.zeros(3, 91, 3), torch.eye(4), VIEW)
    with pytest.raises(ValueError, match="face_depth"):  # depths without the landmarks they belong to
        FitTargets(torch.zeros(3, 91, 3), K, VIEW, face_depth=torch.zeros(3, 478))
    mesh = torch.zeros(3, 478, 3)
    with pytest.raises(ValueError, match="face_depth"):
        FitTargets(torch.zeros(3, 91, 3), K, VIEW, face_mesh=mesh, face_depth=torch.zeros(3, 10))
    depth = torch.full((3, 478), float("nan"))
    t = FitTargets(torch.zeros(3, 91, 3), K, VIEW, face_mesh=mesh, face_depth=depth)
    assert torch.equal(t.face_depth, torch.zeros(3, 478))


def test_an_arm_far_outside_the_robust_scale_is_pulled_onto_its_2d_points(anny_model, clip):
    """MediaPipe's 3D world landmarks can lift an arm out to the side while its 2D points show it
    folded (taiji: 6% of the frames, bench/results/align_before.md). Started there, with 3D
    landmarks that agree with the wrong arm, the arm lies ~4 Geman-McClure sigmas from its 2D
    points, where the robust term has no gradient left: the narrow-scale stages alone keep it
    there; the wide first stage brings it in."""
    lifted = clip.map(lambda t: t.clone())
    upperarm = anny_model.pose_joint_names.index("upperarm01.R")
    lifted.joints[:, upperarm] += torch.tensor([0.0, 0.0, 2.2])
    targets = dataclasses.replace(
        targets_from_params(anny_model, clip, K, VIEW),
        pose_world=targets_from_params(anny_model, lifted, K, VIEW).pose_world,
    )
    arm = [14, 16]  # right elbow and wrist
    targets.keypoints[:, arm, 2] = 0.6  # a fast arm: the 2D detector is unsure of it too

    def arm_error(params) -> float:
        """Worst 2D error of the arm's joints over the clip, in person heights."""
        kp, _ = anny_model.posed_keypoints(params)
        uv = project_points(to_camera(kp, VIEW), K)
        err = (uv[:, arm] - targets.keypoints[:, arm, :2]).norm(dim=-1).amax(dim=1)
        return float((err / targets.person_scale()).max())

    config = fast_config()
    assert arm_error(lifted) > 3.5 * config.sigma_2d
    narrow_only = dataclasses.replace(config, stages=tuple(s for s in config.stages if s.sigma_scale == 1))
    stuck = fit_sequence(anny_model, targets, init=lifted, config=narrow_only).params
    fitted = fit_sequence(anny_model, targets, init=lifted, config=config).params
    assert arm_error(stuck) > 3 * config.sigma_2d
    assert arm_error(fitted) < 0.3 * config.sigma_2d


def test_hands_are_turned_to_the_detected_palm_again_after_the_body_stages(anny_model, clip):
    """The body stages twist the forearms; a hand turned to its palm for the initial estimate's
    forearm turns with them. The hands stage first turns each hand to the detected palm again."""
    targets = targets_from_params(anny_model, clip, K, VIEW)
    wrists = [i - 1 for i, name in enumerate(anny_model.joint_names) if name in ("wrist.L", "wrist.R")]
    twisted = clip.map(lambda t: t.clone())
    twisted.joints[:, wrists] += torch.tensor([0.0, 0.6, 0.3])
    hands = dataclasses.replace(next(s for s in default_stages() if s.name == "hands"), iterations=0)
    assert hands.orient_hands_first

    def run(stage):
        config = FitConfig(stages=(stage,), hand_depth_scale=1.0)  # exact depths
        return fit_sequence(anny_model, targets, init=twisted, config=config).params

    kept = run(dataclasses.replace(hands, orient_hands_first=False))
    turned = run(hands)
    assert torch.equal(kept.joints, twisted.joints)
    before, after = mpjpe(anny_model, twisted, clip), mpjpe(anny_model, turned, clip)
    # Not exactly 0: the detected palm is lifted to 3D at the wrist's depth (weak perspective).
    assert after["hands"] < 0.25 * before["hands"]


def test_a_frame_without_a_face_turns_its_head_to_the_pose_face_points(anny_model, clip):
    """Where the face mesh found no face (a head turned away), the pose model's nose, eyes and
    ears still turn the head, also in stages that give the face group its own weight."""
    from eva_engine.align.evaluate import head_rotation_error
    from eva_engine.align.targets import POSE_FACE

    targets = targets_from_params(anny_model, clip, K, VIEW)
    targets.keypoints[2, KEYPOINT_GROUPS["face"], 2] = 0.0
    assert targets.keypoints[2, list(POSE_FACE), 2].gt(0).all()
    start = clip.map(lambda t: t.clone())
    start.joints[2, anny_model.pose_joint_names.index("head"), 1] += 0.5  # 29 degrees of yaw
    refine = next(s for s in default_stages() if s.name == "refine")
    stage = dataclasses.replace(refine, optimize=("face",), iterations=40, smooth=0.0, face_z=0.0)
    result = fit_sequence(anny_model, targets, init=start, config=FitConfig(stages=(stage,)))
    assert head_rotation_error(anny_model, result.params[2], clip[2]) < 5.0


def test_the_body_stages_ignore_the_face_points_of_a_frame_without_a_face(anny_model, clip):
    """Where no face was found the pose model's face points turn the head, in stages that move
    it; in the body stages (head not free) they would bend the body toward guessed points."""
    from eva_engine.align.objective import FitProblem
    from eva_engine.align.targets import POSE_FACE

    targets = targets_from_params(anny_model, clip, K, VIEW)
    targets.keypoints[2, KEYPOINT_GROUPS["face"], 2] = 0.0
    moved = dataclasses.replace(targets, keypoints=targets.keypoints.clone())
    moved.keypoints[2, list(POSE_FACE), :2] += 40.0  # guessed points far off
    stages = {s.name: s for s in default_stages()}
    for name, counts in (("body", False), ("refine", True)):
        problems = [FitProblem(anny_model, t, FitConfig(), clip) for t in (targets, moved)]
        losses = [float(p.loss(stages[name])) for p in problems]
        assert (losses[0] != losses[1]) == counts, (name, losses)
