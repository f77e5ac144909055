"""The expression-fidelity measures: mouth and eye opening from face-mesh landmarks, their
agreement over frames, and the fitted expression's error per facial-action group."""

from __future__ import annotations

import math

import pytest
import torch

from eva_engine.eval.expression_fidelity import EYES, MOUTH, SCALE, agreement, openings


def face(mouth: float, eyes: float, scale: float = 100.0) -> torch.Tensor:
    """[478, 3] landmarks with the given inner-lip and lid gaps (pixels) and eye-corner distance."""
    lm = torch.zeros(478, 3)
    lm[:, 2] = 1.0
    lm[SCALE[0], :2] = torch.tensor([0.0, 0.0])
    lm[SCALE[1], :2] = torch.tensor([scale, 0.0])
    lm[MOUTH[0], :2] = torch.tensor([50.0, 60.0])
    lm[MOUTH[1], :2] = torch.tensor([50.0, 60.0 + mouth])
    for top, bottom in EYES:
        lm[top, :2] = torch.tensor([20.0, -eyes / 2])
        lm[bottom, :2] = torch.tensor([20.0, eyes / 2])
    return lm


def test_openings_are_gaps_over_the_eye_corner_distance():
    lm = torch.stack([face(10.0, 8.0), face(30.0, 0.0, scale=200.0)])
    got = openings(lm)
    torch.testing.assert_close(got["mouth"], torch.tensor([0.10, 0.15], dtype=torch.float64))
    torch.testing.assert_close(got["eyes"], torch.tensor([0.08, 0.0], dtype=torch.float64))


def test_openings_of_missing_or_degenerate_faces_are_nan():
    lm = torch.stack([face(10.0, 8.0), face(10.0, 8.0, scale=0.0), face(10.0, 8.0)])
    got = openings(lm, found=torch.tensor([True, True, False]))
    assert math.isfinite(float(got["mouth"][0]))
    assert torch.isnan(got["mouth"][1:]).all() and torch.isnan(got["eyes"][1:]).all()
    with pytest.raises(ValueError, match="478"):
        openings(torch.zeros(2, 10, 3))


def test_agreement_of_a_damped_copy():
    target = torch.tensor([0.0, 0.1, 0.2, 0.05, 0.3, float("nan")], dtype=torch.float64)
    stage = 0.5 * target + 0.02
    stage[0] = float("nan")
    a = agreement(target, stage)
    assert a.frames == 4  # the NaN of either side is left out
    assert a.r == pytest.approx(1.0)
    assert a.range_ratio == pytest.approx(0.5)
    assert a.full_range_ratio == pytest.approx(0.5)


def test_the_full_range_sees_a_blink_the_spread_leaves_out():
    # 40 open frames, one closed: the closed frame is under the 5th percentile
    target = torch.cat([0.1 + 0.01 * torch.linspace(0, 1, 40), torch.tensor([0.0])]).double()
    kept, missed = target.clone(), target.clone()
    missed[-1] = 0.1  # the render keeps that eye open
    a, b = agreement(target, kept), agreement(target, missed)
    assert a.full_range_ratio == pytest.approx(1.0)
    assert b.full_range_ratio == pytest.approx(0.01 / 0.11, rel=1e-3)
    assert a.range_ratio == pytest.approx(b.range_ratio, rel=0.2)  # the spread barely sees it


def test_agreement_without_variation_or_frames_is_nan():
    flat = agreement(torch.tensor([0.1, 0.2, 0.3, 0.4]), torch.full((4,), 0.2))
    assert math.isnan(flat.r) and flat.range_ratio == 0.0
    few = agreement(torch.tensor([0.1, 0.2]), torch.tensor([0.1, 0.2]))
    assert few.frames == 2 and math.isnan(few.r) and math.isnan(few.range_ratio)
    assert math.isnan(few.full_range_ratio) and flat.full_range_ratio == 0.0
    with pytest.raises(ValueError):
        agreement(torch.zeros(3), torch.zeros(4))


def test_expression_error_by_group(anny_model):
    from eva_engine.align.evaluate import expression_error_by_group

    names = list(anny_model.expression_names)
    truth = anny_model.default_params(2)
    truth.expression[:, names.index("jawOpen")] = 0.6
    truth.expression[:, names.index("eyeBlinkLeft")] = 0.9
    exact = expression_error_by_group(anny_model, truth, truth)
    assert exact["jaw"] == pytest.approx(0.0, abs=1e-6) and exact["lids"] == pytest.approx(0.0, abs=1e-6)
    assert exact["jaw_neutral"] > 1.0 and exact["lids_neutral"] > 1.0
    assert math.isnan(exact["brows"]) and math.isnan(exact["lips"])  # nothing true to recover there
    # A fit with the jaw right and no blink: the jaw's error is 0, the lids' that of a neutral face.
    fitted = truth.map(lambda t: t.clone())
    fitted.expression[:, names.index("eyeBlinkLeft")] = 0.0
    got = expression_error_by_group(anny_model, fitted, truth)
    assert got["jaw"] == pytest.approx(0.0, abs=1e-6)
    assert got["lids"] == pytest.approx(got["lids_neutral"], rel=1e-5)
