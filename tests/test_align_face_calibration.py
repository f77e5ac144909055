"""The face-mesh detector's calibration (``align.face_calibration``): offsets in the face's own
frame, carried into the image by the detected eye corners; and the fit's face stage with it."""

from __future__ import annotations

import math

import numpy as np
import torch

from eva_engine.align.face_calibration import DetectorCalibration, in_face_frame, random_expressions

E = 3


def _calibration() -> DetectorCalibration:
    bias = torch.tensor([[0.1, 0.0], [0.0, -0.05]])  # landmarks 13 and 14
    gain = torch.zeros(E, 2, 2)
    gain[0, 1] = torch.tensor([0.0, 0.2])  # action 0 moves landmark 14's reading down the face
    return DetectorCalibration(torch.tensor([13, 14]), bias, gain)


def _corners(right, left, conf=(1.0, 1.0)) -> torch.Tensor:
    return torch.tensor([[[*right, conf[0]], [*left, conf[1]]]], dtype=torch.float32)


def test_offsets_scale_with_the_eye_corner_distance_and_turn_with_the_face():
    cal = _calibration()
    expression = torch.tensor([[0.5, 0.0, 0.0]])
    upright = cal.offsets(expression, _corners((100.0, 100.0), (200.0, 100.0)))
    # 0.1 of a 100 px eye line along it; 0.5 * 0.2 - 0.05 = 0.05 of it towards the chin (image down).
    assert torch.allclose(upright, torch.tensor([[[10.0, 0.0], [0.0, 5.0]]]), atol=1e-5)
    half = cal.offsets(expression, _corners((100.0, 100.0), (150.0, 100.0)))
    assert torch.allclose(half, upright / 2, atol=1e-5)
    # The head rolled a quarter turn (the eye line points down the image): the offsets turn with it.
    rolled = cal.offsets(expression, _corners((100.0, 100.0), (100.0, 200.0)))
    assert torch.allclose(rolled, torch.tensor([[[0.0, 10.0], [-5.0, 0.0]]]), atol=1e-5)


def test_no_offset_without_both_eye_corners_or_for_an_uncalibrated_landmark():
    cal = _calibration()
    expression = torch.ones(1, E)
    missing = cal.offsets(expression, _corners((100.0, 100.0), (200.0, 100.0), conf=(1.0, 0.0)))
    assert torch.equal(missing, torch.zeros(1, 2, 2))
    other = cal.aligned(torch.tensor([14, 7, 13]))  # the points' order; 7 has no calibration
    assert torch.equal(other.landmarks, torch.tensor([14, 7, 13]))
    read = other.offsets(expression, _corners((100.0, 100.0), (200.0, 100.0)))
    full = cal.offsets(expression, _corners((100.0, 100.0), (200.0, 100.0)))
    assert torch.equal(read[0, 1], torch.zeros(2))
    assert torch.equal(read[0, 0], full[0, 1]) and torch.equal(read[0, 2], full[0, 0])


def test_offsets_are_finite_and_differentiable_in_the_expression_even_with_corners_on_one_pixel():
    cal = _calibration()
    expression = torch.full((2, E), 0.3, requires_grad=True)
    corners = torch.cat([_corners((100.0, 100.0), (200.0, 100.0)), _corners((50.0, 50.0), (50.0, 50.0))])
    out = cal.offsets(expression, corners)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(expression.grad).all()
    assert torch.equal(out[1], torch.zeros(2, 2))  # a zero-length eye line reads as no offset


def test_the_face_frame_is_the_inverse_of_the_offsets():
    """What ``build_calibration`` measures (``in_face_frame``) and what the fit adds (``offsets``)
    are the same map read both ways, for any roll and size of the face."""
    rng = np.random.default_rng(0)
    detected = np.zeros((478, 2))
    angle = 0.7
    detected[33] = (300.0, 200.0)
    detected[263] = detected[33] + 80.0 * np.array([math.cos(angle), math.sin(angle)])
    pixels = rng.normal(size=(2, 2)) * 4.0
    local = in_face_frame(pixels, detected)
    cal = DetectorCalibration(torch.tensor([13, 14]), torch.from_numpy(local).float(), torch.zeros(E, 2, 2))
    corners = torch.from_numpy(np.stack([np.append(detected[33], 1.0), np.append(detected[263], 1.0)]))[None]
    back = cal.offsets(torch.zeros(1, E), corners.float())[0]
    assert np.allclose(back.numpy(), pixels, atol=1e-4)


def test_random_expressions_are_sparse_in_range_and_start_neutral():
    names = ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight", *(f"a{i}" for i in range(20))]
    expr = random_expressions(names, 50, np.random.default_rng(0))
    assert expr.shape == (50, len(names)) and not expr[0].any()
    assert (expr >= 0).all() and (expr <= 1).all()
    assert ((expr[1:] > 0).sum(1) <= 6).all() and ((expr[1:] > 0).sum(1) >= 1).all()


def test_the_calibration_of_anny_reads_the_jaw_in_the_inner_lips_and_leaves_the_eyes_alone(anny_model):
    """Built by ``eva setup`` (else here, once, about a minute): the inner lips' readings answer the
    jaw, beyond the surface points' own motion; the eye outlines are left uncalibrated."""
    from eva_engine.align.face_calibration import EYE_CONTOURS, load_calibration
    from eva_engine.align.face_mesh import load_correspondence

    cal = load_calibration(anny_model, load_correspondence(anny_model))
    assert cal is not None
    rows = {int(k): i for i, k in enumerate(cal.landmarks)}
    jaw = list(anny_model.expression_names).index("jawOpen")
    eyes = [rows[k] for k in EYE_CONTOURS if k in rows]
    assert eyes and torch.equal(cal.gain[:, eyes], torch.zeros_like(cal.gain[:, eyes]))
    assert torch.equal(cal.bias[eyes], torch.zeros_like(cal.bias[eyes]))
    lips = [rows[k] for k in (13, 14, 82, 87, 312, 317) if k in rows]
    assert float(cal.gain[jaw, lips].norm(dim=-1).max()) > 0.01  # over 1% of the eye-corner distance
    assert torch.isfinite(cal.gain).all() and torch.isfinite(cal.bias).all()
