"""Hands through the whole clip: frames without a hand detection get the hand's pose from their
neighbours, a hand detected on the wrong side is dropped, the palm starts on the right side, and
the hand joints' anatomy prior penalises what fingers cannot do."""

from __future__ import annotations

import math

import pytest
import torch

from eva_engine.align import FitConfig, targets_from_params
from eva_engine.align.hands import (
    HandTrackConfig,
    articulation_prior,
    fill_hand_gaps,
    hand_found,
    hand_joint_sides,
    reject_wrong_hands,
)
from eva_engine.align.initial import initial_estimate
from eva_engine.body import KEYPOINT_GROUPS
from eva_engine.render import intrinsics, look_at


def curling_clip(body, n: int = 9):
    """n frames, 10 fps: the left hand's fingers curl from straight to bent at a steady rate."""
    params = body.default_params(n)
    left, _ = hand_joint_sides(body)
    names = body.pose_joint_names
    curl = [j for j in left.tolist() if "finger" in names[j] and not names[j].startswith("finger1")]
    for i in range(n):
        params.joints[i, curl, 0] = 1.2 * i / (n - 1)
    return params, torch.arange(n, dtype=torch.float64) / 10.0


def test_missing_frames_are_interpolated_with_a_confidence(anny_model):
    truth, times = curling_clip(anny_model)
    fitted = truth.map(lambda t: t.clone())
    left, right = hand_joint_sides(anny_model)
    gap = [3, 4, 5]
    fitted.joints[torch.tensor(gap)[:, None], left] = 0.0  # what a fit leaves there: rest hands
    found = torch.ones(len(times), 2, dtype=torch.bool)
    found[gap, 0] = False
    filled, conf = fill_hand_gaps(anny_model, fitted, found, times)
    err_before = (fitted.joints[gap][:, left] - truth.joints[gap][:, left]).norm(dim=-1).mean()
    err_after = (filled.joints[gap][:, left] - truth.joints[gap][:, left]).norm(dim=-1).mean()
    assert err_after < 0.05 * err_before  # a steady curl is interpolated almost exactly
    # Confidence: 1 where detected, lower inside the gap and lowest in its middle.
    assert torch.equal(conf[found], torch.ones(int(found.sum())))
    assert 0 < conf[4, 0] < conf[3, 0] < 1 and conf[3, 0] == pytest.approx(float(conf[5, 0]))
    # The other hand and the detected frames are untouched.
    keep = [i for i in range(len(times)) if i not in gap]
    assert torch.equal(filled.joints[keep], fitted.joints[keep])
    assert torch.equal(filled.joints[:, right], fitted.joints[:, right])


def test_long_gaps_and_clip_ends_are_not_invented(anny_model):
    truth, times = curling_clip(anny_model, n=9)
    found = torch.zeros(9, 2, dtype=torch.bool)
    found[[0, 8], 0] = True  # 0.8 s apart
    _, conf = fill_hand_gaps(anny_model, truth, found, times, HandTrackConfig(max_gap=0.5))
    assert conf[1:8, 0].eq(0).all() and conf[:, 1].eq(0).all()
    found = torch.zeros(9, 2, dtype=torch.bool)
    found[4, 0] = True  # one detection: nothing before or after it to interpolate with
    filled, conf = fill_hand_gaps(anny_model, truth, found, times)
    assert conf[:, 0].tolist() == [0, 0, 0, 0, 1, 0, 0, 0, 0]
    assert torch.equal(filled.joints, truth.joints)


def test_a_hand_detected_on_the_wrong_side_is_dropped(anny_model):
    params = anny_model.default_params(2)
    K, view = intrinsics(256, 256, 40.0), look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0))
    kp = targets_from_params(anny_model, params, K, view, (256, 256)).keypoints.clone()
    left, right = KEYPOINT_GROUPS["left_hand"], KEYPOINT_GROUPS["right_hand"]
    kp[1, left] = kp[1, right].clone()  # frame 1: the right hand reported as the left one
    cleaned, rejected = reject_wrong_hands(kp)
    assert rejected.tolist() == [[False, False], [True, False]]
    assert hand_found(cleaned).tolist() == [[True, True], [False, True]]
    assert torch.equal(cleaned[0], kp[0])


def test_palm_orientation_starts_on_the_detected_side(anny_model):
    """A hand turned palm-out by 150 deg: the initial estimate turns the model's palm to match
    the detection (wrist-centred hand points within 2 cm) instead of starting from rest."""
    truth = anny_model.default_params(1)
    wrist = anny_model.joint_names.index("wrist.L") - 1
    truth.joints[0, wrist] = torch.tensor([0.0, math.radians(150.0), 0.0])
    K, view = intrinsics(512, 512, 40.0), look_at((0.0, 0.3, 2.0), (0.3, 0.1, 0.0))
    targets = targets_from_params(anny_model, truth, K, view, (512, 512))
    sl = KEYPOINT_GROUPS["left_hand"]

    def hand_error(params) -> float:
        with torch.no_grad():
            a, b = anny_model.posed_keypoints(params)[0][0, sl], anny_model.posed_keypoints(truth)[0][0, sl]
        return float(((a - a[0]) - (b - b[0])).norm(dim=-1).mean())

    plain = initial_estimate(anny_model, targets, FitConfig(orient_hands=False, hand_depth_scale=1.0))
    oriented = initial_estimate(anny_model, targets, FitConfig(hand_depth_scale=1.0))
    assert hand_error(plain) > 0.05 and hand_error(oriented) < 0.02, (hand_error(plain), hand_error(oriented))


def test_articulation_prior_penalises_what_fingers_cannot_do(anny_model):
    prior = articulation_prior(anny_model)
    names = anny_model.pose_joint_names
    assert len(prior.joints) == 2 * (
        4 * 4 + 2
    )  # per hand: 4 fingers x (metacarpal, MCP, PIP, DIP), thumb MCP, IP
    for j, proj in zip(prior.joints.tolist(), prior.projectors, strict=True):
        if names[j].endswith("-2.L") and not names[j].startswith("finger1"):  # a PIP: a hinge
            flex = torch.linalg.svd(torch.eye(3) - proj).U[:, 0]  # the one free axis
            assert float((proj @ flex).norm()) < 1e-5
            side = torch.linalg.cross(flex, torch.tensor([0.0, 0.0, 1.0]))
            assert float((proj @ (side / side.norm())).norm()) > 0.5


def test_expression_smoothing_over_time():
    from eva_engine.align.clip import smooth_over_time

    times = torch.arange(20, dtype=torch.float64) / 25.0
    steady = torch.linspace(0, 1, 20)[:, None].repeat(1, 3)
    jitter = steady + 0.05 * torch.tensor([(-1.0) ** i for i in range(20)])[:, None]
    out = smooth_over_time(jitter, times, 0.04)
    inner = slice(3, -3)  # away from the clip's ends
    assert (out[inner] - steady[inner]).abs().max() < 0.5 * (jitter[inner] - steady[inner]).abs().max()
    assert torch.equal(smooth_over_time(jitter, times, 0.0), jitter)
    assert torch.allclose(smooth_over_time(torch.ones(20, 2), times, 0.04), torch.ones(20, 2))
