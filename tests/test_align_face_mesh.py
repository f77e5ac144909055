"""The face-mesh correspondence: MediaPipe's landmarks on the body model's face, consistent with
what MediaPipe finds on a rendered face, and the dense face term in fitting."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from eva_engine.align import face_mesh
from eva_engine.align.face_mesh import (
    NUM_LANDMARKS,
    detect_face_mesh,
    load_correspondence,
    render_face,
    shared_painted_face,
)
from eva_engine.body import SIDED_PART_NAMES
from eva_engine.geometry import project_points, to_camera


@pytest.fixture(scope="module")
def correspondence(anny_model):
    corr = load_correspondence(anny_model)  # built by `eva setup`, else here once
    assert corr is not None
    return corr


def test_landmarks_land_on_the_face(anny_model, correspondence):
    c = correspondence
    assert c.faces.shape == (NUM_LANDMARKS,) and c.barycentric.shape == (NUM_LANDMARKS, 3)
    assert int(c.valid.sum()) >= 350  # most of the 468 surface landmarks
    assert torch.allclose(c.barycentric.sum(1), torch.ones(NUM_LANDMARKS), atol=1e-5)
    assert (c.barycentric >= 0).all()
    face = SIDED_PART_NAMES.index("face")
    corners = anny_model.sided_part_ids[anny_model.faces[c.faces[c.valid]]]
    assert (corners == face).all()
    # Iris points and the silhouette oval are not used (gaze; sliding outline points).
    assert not c.valid[468:].any()
    terms = c.vertex_terms(anny_model.faces)
    assert len(terms) == int(c.valid.sum()) and all(abs(sum(t.values()) - 1) < 1e-5 for t in terms.values())


def test_reprojection_on_a_rendered_face(anny_model, correspondence):
    """A view the correspondence was not built from (5 deg right, 5 deg up), 512 px: MediaPipe's
    landmarks and the projected correspondence points agree to under 1.5 px (median). The render
    comes from a shared renderer, which renders the same after it has rendered something else
    (the correspondence and the calibration build from one)."""
    with shared_painted_face(anny_model) as renderer:
        assert renderer() is renderer()
        render_face(anny_model, ((0.0, 0.0),), expression={"jawOpen": 1.0}, renderer=renderer())
        r = render_face(anny_model, ((5.0, 5.0),), renderer=renderer())[0]
        again = render_face(anny_model, ((5.0, 5.0),), renderer=renderer())[0]
    assert np.array_equal(r["rgb"], again["rgb"]) and torch.equal(r["face_id"], again["face_id"])
    pts = detect_face_mesh(r["rgb"])
    assert pts is not None
    c = correspondence
    corners = r["vertices"].double()[anny_model.faces[c.faces]]  # [478, 3, 3]
    points = (c.barycentric.double()[..., None] * corners).sum(1)
    uv = project_points(to_camera(points[None], r["viewmat"].double()), r["K"].double())[0].numpy()
    err = np.linalg.norm(uv - pts, axis=1)[c.valid.numpy()]
    assert np.median(err) < 1.5, np.median(err)
    assert np.percentile(err, 90) < 4.0, np.percentile(err, 90)


def test_the_shared_renderer_opens_only_when_asked_for(anny_model, correspondence, monkeypatch):
    """With the cache present (the fixture), loading never pays a renderer's texture bake."""
    opened = []
    monkeypatch.setattr(face_mesh, "painted_face_renderer", lambda *a: opened.append(a))
    with shared_painted_face(anny_model) as renderer:
        assert load_correspondence(anny_model, renderer=renderer) is not None
    assert opened == []


def test_posed_points_fast_path_matches_posing_the_mesh(anny_model, correspondence):
    reg, landmarks = correspondence.regressor(anny_model)
    g = torch.Generator().manual_seed(0)
    params = anny_model.default_params(3)
    params.joints.copy_(torch.randn(params.joints.shape, generator=g) * 0.2)
    params.expression.copy_(torch.rand(params.expression.shape, generator=g) * 0.5)
    params.transl.copy_(torch.randn(3, 3, generator=g))
    fast = anny_model.posed_points(params, reg)
    out = anny_model(params)
    slow = reg(out.vertices, out.joints)
    assert fast.shape == (3, len(landmarks), 3)
    torch.testing.assert_close(fast, slow, atol=2e-5, rtol=0)


def _face_targets(model, correspondence, params, K, view, depth_scale):
    """Exact face-mesh targets of ``params``: projected landmarks and their relative depths in
    pixels, as MediaPipe reports them (divided by ``depth_scale``, which the fit multiplies in)."""
    from eva_engine.align.evaluate import targets_from_params

    reg, landmarks = correspondence.regressor(model)
    with torch.no_grad():
        cam = to_camera(model.posed_points(params, reg), view)
    f = params.batch_size
    mesh = torch.zeros(f, NUM_LANDMARKS, 3)
    mesh[:, landmarks, :2] = project_points(cam, K)
    mesh[:, landmarks, 2] = 1.0
    depth = torch.zeros(f, NUM_LANDMARKS)
    z = cam[..., 2]
    depth[:, landmarks] = (z - z.mean(1, keepdim=True)) * K[0, 0] / z.mean(1, keepdim=True) / depth_scale
    base = targets_from_params(model, params, K, view, image_size=(512, 512))
    return dataclasses.replace(base, face_mesh=mesh, face_depth=depth)


def _head_error_deg(model, a, b, view) -> torch.Tensor:
    """[F, 3] the rotation between the head's rotations of ``a`` and ``b`` as a rotation vector
    in camera axes, in degrees: x pitch, y yaw, z roll (about the optical axis)."""
    from eva_engine.align.evaluate import head_rotation_delta

    return torch.rad2deg(head_rotation_delta(model, a, b) @ view[:3, :3].T)


def test_face_depths_turn_a_head_back(anny_model, correspondence):
    """The face mesh's relative depths alone (no 2D term) turn a head that starts 17 degrees off
    in pitch and yaw back (roll about the optical axis changes no depth); they do not move the
    expression, which is the 2D terms' to fit."""
    from eva_engine.align.fit import fit_sequence
    from eva_engine.align.stages import FitConfig, FitStage
    from eva_engine.render import intrinsics, orbit_camera

    K, view = intrinsics(512, 512, 30.0), orbit_camera(0.0, 0.0, 1.0, target=(0.0, 0.6, 0.0))
    names = anny_model.pose_joint_names
    truth = anny_model.default_params(3)
    head = names.index("head")
    truth.joints[:, head] = torch.tensor([[0.0, 0.3, 0.0], [0.2, -0.2, 0.0], [-0.15, 0.0, 0.1]])
    truth.expression[:, anny_model.expression_names.index("jawOpen")] = 0.5
    config = FitConfig()
    targets = _face_targets(anny_model, correspondence, truth, K, view, config.face_depth_scale)
    start = truth.map(lambda t: t.clone())
    start.joints[:, head] += torch.tensor([0.3, 0.3, 0.0])
    stage = FitStage("depth", 40, ("face", "expression"), w_pose=0.0, face_z=10.0, smooth=0.0)
    config = dataclasses.replace(config, stages=(stage,))
    result = fit_sequence(anny_model, targets, init=start, config=config)
    before = _head_error_deg(anny_model, start, truth, view)
    after = _head_error_deg(anny_model, result.params, truth, view)
    assert (before[:, :2].abs() > 15).all() and (after[:, :2].abs() < 1.0).all(), (before, after)
    assert torch.equal(result.params.expression, start.expression)


def test_face_depth_term_is_finite_on_degenerate_targets(anny_model, correspondence):
    """Huge, zero and missing depths, and a face almost at the camera: finite loss and gradients."""
    from eva_engine.align.objective import FitProblem
    from eva_engine.align.stages import FitConfig, FitStage
    from eva_engine.render import intrinsics, orbit_camera

    K, view = intrinsics(512, 512, 30.0), orbit_camera(0.0, 0.0, 1.0, target=(0.0, 0.6, 0.0))
    params = anny_model.default_params(4)
    params.transl[3, 2] = 0.99  # the face just in front of the camera
    targets = _face_targets(anny_model, correspondence, params, K, view, 1.0)
    targets.face_depth[0] = 1e9
    targets.face_depth[1] = 0.0
    targets.face_mesh[2, :, 2] = 0.0  # no face found
    stage = FitStage("depth", 1, ("root", "transl", "face"), w_pose=0.0, face_z=10.0)
    problem = FitProblem(anny_model, targets, FitConfig(stages=(stage,)), params)
    for g in ("root", "transl", "face"):
        problem.values[g].requires_grad_(True)
    loss = problem.loss(stage)
    loss.backward()
    assert torch.isfinite(loss)
    for g in ("root", "transl", "face"):
        assert torch.isfinite(problem.values[g].grad).all(), g


def test_opening_term_sees_the_gap_not_an_offset(anny_model, correspondence):
    """The opening term compares lid and inner-lip gaps: landmarks shifted as a whole cost
    nothing, one upper lid lowered costs, a frame without a face costs nothing, and a huge
    shift keeps the loss and its gradient finite. The targets are the model's own points, so the
    detector's calibration is off here (with it, a shift as a whole still costs nothing more)."""
    from eva_engine.align.face_mesh import OPENING_PAIRS
    from eva_engine.align.objective import FitProblem
    from eva_engine.align.stages import FitConfig, FitStage
    from eva_engine.render import intrinsics, orbit_camera

    K, view = intrinsics(512, 512, 30.0), orbit_camera(0.0, 0.0, 1.0, target=(0.0, 0.6, 0.0))
    params = anny_model.default_params(1)
    stage = FitStage("openings", 1, ("face", "expression"), w_pose=0.0, w_openings=10.0, limits=0.0)

    def loss_of(change, calibrated: bool = False) -> tuple[float, bool]:
        targets = _face_targets(anny_model, correspondence, params, K, view, 1.0)
        change(targets.face_mesh[0])
        config = FitConfig(stages=(stage,), detector_calibration=calibrated)
        problem = FitProblem(anny_model, targets, config, params)
        for g in ("face", "expression"):
            problem.values[g].requires_grad_(True)
        loss = problem.loss(stage)
        loss.backward()
        finite = all(torch.isfinite(problem.values[g].grad).all() for g in ("face", "expression"))
        return float(loss.detach()), bool(torch.isfinite(loss)) and finite

    def shift(mesh, by):
        mesh[:, :2] += torch.tensor(by)

    def lower_a_lid(mesh):
        mesh[OPENING_PAIRS[1][0], 1] += 5.0

    def lose_the_face(mesh):
        mesh[:, 2] = 0.0

    shifted, lid, lost, huge = (
        loss_of(lambda m: shift(m, [7.0, -4.0])),
        loss_of(lower_a_lid),
        loss_of(lose_the_face),
        loss_of(lambda m: shift(m, [1e6, -1e6])),
    )
    assert all(ok for _, ok in (shifted, lid, lost, huge))
    assert shifted[0] < 1e-6 < lid[0] and lost[0] == 0.0
    as_is, moved = loss_of(lambda m: None, True), loss_of(lambda m: shift(m, [7.0, -4.0]), True)
    assert as_is[1] and moved[1] and abs(moved[0] - as_is[0]) < 1e-5 * max(1.0, as_is[0])
