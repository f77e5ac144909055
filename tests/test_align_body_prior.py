"""The body's articulation prior: Anny's second arm bones twist only, the elbow is a hinge, the
bones between chest and arm and the spine's and neck's segments move little; and a fit with it
puts an arm's motion in the bones a person moves, where the keypoints alone leave it anywhere."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import torch

from eva_engine.align.body_prior import CHAIN_BONES, SEGMENT_BONES, body_articulation_prior
from eva_engine.align.evaluate import targets_from_params
from eva_engine.align.fit import fit_sequence
from eva_engine.align.stages import FitConfig, default_stages
from eva_engine.body.rest_axes import rest_axes
from eva_engine.render import intrinsics, orbit_camera


def cost(prior, names, joint: str, rotvec) -> float:
    """The prior's penalty of one joint turned by ``rotvec`` (everything else at rest)."""
    m = prior.joints.tolist().index(names.index(joint))
    r = torch.as_tensor(rotvec, dtype=torch.float32)
    return float(prior.weights[m] * (prior.projectors[m] @ r).square().sum())


def test_the_prior_allows_what_arms_do_and_penalises_what_they_cannot(anny_model):
    prior = body_articulation_prior(anny_model)
    names = anny_model.pose_joint_names
    assert len(prior.joints) == 2 * (3 + len(SEGMENT_BONES)) + len(CHAIN_BONES)
    axes = rest_axes(anny_model, anny_model.default_params(1).shape)
    with torch.no_grad():
        heads = anny_model(anny_model.default_params(1)).joints[0]
    j = {n: heads[i] for i, n in enumerate(anny_model.joint_names)}
    for s in "LR":
        upper = j[f"lowerarm01.{s}"] - j[f"upperarm01.{s}"]
        upper = upper / upper.norm()
        bend = torch.linalg.cross(upper, torch.tensor([0.0, 0.0, 1.0]))
        bend = bend / bend.norm()
        # The upper arm's second bone: a twist is free, a bend half-way along the humerus is not.
        assert cost(prior, names, f"upperarm02.{s}", 0.5 * upper) < 1e-8
        assert cost(prior, names, f"upperarm02.{s}", 0.5 * bend) > 0.2
        # The elbow flexes about its hinge for free, and cannot bend sideways.
        elbow = torch.as_tensor(axes.elbow[s], dtype=torch.float32)
        assert cost(prior, names, f"lowerarm01.{s}", 1.2 * elbow) < 1e-6
        side = torch.linalg.cross(elbow, upper)
        assert cost(prior, names, f"lowerarm01.{s}", 0.5 * side / side.norm()) > 0.2
        # The forearm's second bone carries the pronation.
        fore = torch.as_tensor(axes.forearm[s], dtype=torch.float32)
        assert cost(prior, names, f"lowerarm02.{s}", 0.8 * fore) < 1e-6
        # Clavicle and shoulder bone: any turn costs, less than an arm bone's impossible bend.
        shrug = cost(prior, names, f"clavicle.{s}", 0.5 * bend)
        assert 0.0 < shrug < cost(prior, names, f"upperarm02.{s}", 0.5 * bend)
    # A bend shared by the spine's five segments costs a fifth of the same bend at one.
    spine = [b for b in CHAIN_BONES if b.startswith("spine")]
    one = cost(prior, names, spine[0], [0.5, 0.0, 0.0])
    shared = sum(cost(prior, names, b, [0.5 / len(spine), 0.0, 0.0]) for b in spine)
    assert abs(shared - one / len(spine)) < 1e-6


def test_the_hinge_is_the_subjects_own(anny_model):
    """Built for a subject's shape, the prior lets that subject's elbow flex freely; the default
    shape's hinge is off by degrees, which a right-angled elbow turns into a sideways bend."""
    names = anny_model.pose_joint_names
    shape = torch.zeros(1, anny_model.default_params(1).shape.shape[1])
    shape[0, :] = torch.tensor([1.0, 0.9, 1.0, 1.0, 0.1, 0.9])[: shape.shape[1]]
    elbow = torch.as_tensor(rest_axes(anny_model, shape).elbow["L"], dtype=torch.float32)
    own = body_articulation_prior(anny_model, shape)
    default = body_articulation_prior(anny_model)
    assert cost(own, names, "lowerarm01.L", 1.5 * elbow) < 1e-6
    assert cost(default, names, "lowerarm01.L", 1.5 * elbow) > 100 * max(
        cost(own, names, "lowerarm01.L", 1.5 * elbow), 1e-8
    )


def test_the_penalty_is_finite_with_finite_gradients_at_extreme_poses(anny_model):
    prior = body_articulation_prior(anny_model)
    rotvecs = torch.zeros(3, len(anny_model.pose_joint_names), 3)
    rotvecs[1] = 1e4  # absurd turns everywhere
    rotvecs[2] = 1e-30  # next to nothing
    rotvecs.requires_grad_(True)
    value = prior.penalty(rotvecs)
    value.backward()
    assert torch.isfinite(value) and torch.isfinite(rotvecs.grad).all()


def test_a_model_without_annys_bones_gets_an_empty_prior():
    smplx_like = SimpleNamespace(joint_names=["pelvis", "left_hip", "spine1", "left_elbow", "left_wrist"])
    prior = body_articulation_prior(smplx_like)
    assert prior.joints.numel() == 0 and prior.projectors.shape == (0, 3, 3)


def test_a_fit_with_the_prior_takes_the_arms_motion_back_to_the_bones_that_made_it(anny_model):
    """Arms raised and elbows bent by the bones a person moves (upperarm01, the elbow's hinge);
    the fit starts from that pose with the clavicles, shoulder bones and upper arms' second bones
    turned as well, the spread a free fit leaves, and fits the exact keypoints again. Without the
    prior most of the spread stays (the keypoints barely see it); with it the helper bones return
    toward rest and the arms' skin toward the truth."""
    frames = 2
    names = anny_model.pose_joint_names
    axes = rest_axes(anny_model, anny_model.default_params(1).shape)
    truth = anny_model.default_params(frames)
    for s, sign in (("L", 1.0), ("R", -1.0)):
        elbow = torch.as_tensor(axes.elbow[s], dtype=torch.float32)
        for i in range(frames):
            truth.joints[i, names.index(f"upperarm01.{s}")] = torch.tensor(
                [-0.4 * i, 0.0, sign * (0.3 + 0.2 * i)]
            )
            truth.joints[i, names.index(f"lowerarm01.{s}")] = (0.5 + 0.4 * i) * elbow
    targets = targets_from_params(anny_model, truth, intrinsics(256, 256, 40.0), orbit_camera(0.0, 0.0, 3.0))
    helpers = [names.index(f"{b}.{s}") for b in ("clavicle", "shoulder01", "upperarm02") for s in "LR"]
    spread = truth.map(lambda t: t.clone())
    g = torch.Generator().manual_seed(0)
    spread.joints[:, helpers] += 0.15 * torch.randn(frames, len(helpers), 3, generator=g)
    dom = anny_model.skinning_weights.argmax(dim=1).tolist()
    arms = torch.tensor([anny_model.joint_names[j].startswith(("upperarm", "lowerarm")) for j in dom])
    with torch.no_grad():
        true_arms = anny_model(truth).vertices[:, arms]
    refine = next(s for s in default_stages() if s.name == "refine")

    def fit(weight: float) -> tuple[float, float]:
        stage = dataclasses.replace(refine, iterations=60, body_prior=weight)
        params = fit_sequence(anny_model, targets, init=spread, config=FitConfig(stages=(stage,))).params
        with torch.no_grad():
            error = (anny_model(params).vertices[:, arms] - true_arms).norm(dim=-1).mean()
        return float(params.joints[:, helpers].norm(dim=-1).mean()), float(error)

    start_turn = float(spread.joints[:, helpers].norm(dim=-1).mean())
    free_turn, free_error = fit(0.0)
    held_turn, held_error = fit(0.3)
    assert held_turn < 0.5 * free_turn and free_turn < start_turn, (start_turn, free_turn, held_turn)
    assert held_error < 0.8 * free_error, (free_error, held_error)
