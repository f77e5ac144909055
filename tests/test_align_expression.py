"""Expressions from the face mesh: a blink and an open jaw reach the fitted face (issue 39).

The painted Anny face is rendered with the eyes closing and the jaw open, MediaPipe's face mesh
runs on the render, and the product's face stage fits the expression from a neutral face. What
is checked is what a viewer sees: the gap between the lids and between the inner lips."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from eva_engine.align.face_mesh import NUM_LANDMARKS, detect_face_mesh, load_correspondence, render_face
from eva_engine.eval.expression_fidelity import EYES, MOUTH, surface_gaps

TRUTH = {"eyeBlinkLeft": 0.8, "eyeBlinkRight": 0.8, "jawOpen": 0.5}


@pytest.fixture(scope="module")
def correspondence(anny_model):
    corr = load_correspondence(anny_model)
    assert corr is not None
    return corr


def _params(model, expression: dict[str, float]):
    return model.params_from_pose({"expression": expression})


def _gaps_mm(model, correspondence, params) -> dict[str, float]:
    """Inner-lip gap and mean lid gap of the posed correspondence points, in mm."""
    reg, landmarks = correspondence.regressor(model)
    mouth, *eyes = (1000 * surface_gaps(model, params, reg, landmarks, (MOUTH, *EYES))[0]).tolist()
    return {"mouth": mouth, "eyes": 0.5 * (eyes[0] + eyes[1])}


def test_jaw_and_blink_move_their_landmarks(anny_model, correspondence):
    """The correspondence puts the lower inner lip on the lower lip and the upper lids on the lids
    (not on the eyeballs, which no blink moves): opening the jaw parts 13-14, a blink closes
    159-145 and 386-374."""
    neutral = _gaps_mm(anny_model, correspondence, _params(anny_model, {}))
    jaw = _gaps_mm(anny_model, correspondence, _params(anny_model, {"jawOpen": 1.0}))
    blink = _gaps_mm(
        anny_model, correspondence, _params(anny_model, {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0})
    )
    assert jaw["mouth"] > neutral["mouth"] + 20.0, (neutral, jaw)
    assert blink["eyes"] < 0.4 * neutral["eyes"], (neutral, blink)
    assert abs(jaw["eyes"] - neutral["eyes"]) < 0.5 and abs(blink["mouth"] - neutral["mouth"]) < 0.5


def test_fit_follows_a_rendered_blink_and_jaw_opening(anny_model, correspondence):
    """From MediaPipe on a render with the eyes 80% closed and the jaw half open, the product's
    stages that move the expression ("face", then "refine", which keeps the coefficients in
    range; from the neutral face, nothing but the face mesh as targets) open the fitted lips and
    close the fitted lids by the true amount, within 20% (issue 39). Measured
    (``bench/results/expressions/one_face.md``): 104% of the lip gap's true change and 92% of
    the lids'; without the opening term 95% and 41%."""
    from eva_engine.align.evaluate import targets_from_params
    from eva_engine.align.fit import fit_sequence
    from eva_engine.align.stages import FitConfig, default_stages

    truth = _params(anny_model, TRUTH)
    r = render_face(anny_model, ((0.0, 0.0),), expression=TRUTH)[0]
    pts = detect_face_mesh(r["rgb"])
    assert pts is not None
    mesh = torch.zeros(1, NUM_LANDMARKS, 3)
    mesh[0, :, :2] = torch.from_numpy(pts).float()
    mesh[0, :, 2] = 1.0
    base = targets_from_params(anny_model, truth, r["K"], r["viewmat"], image_size=(512, 512))
    keypoints = base.keypoints.clone()
    keypoints[..., 2] = 0.0  # nothing but the face mesh
    targets = dataclasses.replace(base, keypoints=keypoints, face_mesh=mesh)
    config = FitConfig(stages=tuple(s for s in default_stages() if s.name in ("face", "refine")))
    fitted = fit_sequence(anny_model, targets, init=_params(anny_model, {}), config=config).params

    neutral = _gaps_mm(anny_model, correspondence, _params(anny_model, {}))
    want = _gaps_mm(anny_model, correspondence, truth)
    got = _gaps_mm(anny_model, correspondence, fitted)
    for measure in ("mouth", "eyes"):
        amplitude, recovered = want[measure] - neutral[measure], got[measure] - neutral[measure]
        assert 0.8 <= recovered / amplitude <= 1.2, (measure, neutral, want, got)
