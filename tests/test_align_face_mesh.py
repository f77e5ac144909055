"""The face-mesh correspondence: MediaPipe's landmarks on the body model's face, consistent with
what MediaPipe finds on a rendered face, and the dense face term in fitting."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eva_engine.align.face_mesh import NUM_LANDMARKS, detect_face_mesh, load_correspondence, render_face
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
    landmarks and the projected correspondence points agree to under 1.5 px (median)."""
    r = render_face(anny_model, ((5.0, 5.0),))[0]
    pts = detect_face_mesh(r["rgb"])
    assert pts is not None
    c = correspondence
    corners = r["vertices"].double()[anny_model.faces[c.faces]]  # [478, 3, 3]
    points = (c.barycentric.double()[..., None] * corners).sum(1)
    uv = project_points(to_camera(points[None], r["viewmat"].double()), r["K"].double())[0].numpy()
    err = np.linalg.norm(uv - pts, axis=1)[c.valid.numpy()]
    assert np.median(err) < 1.5, np.median(err)
    assert np.percentile(err, 90) < 4.0, np.percentile(err, 90)


def test_posed_points_fast_path_matches_posing_the_mesh(anny_model, correspondence):
    from eva_engine.body.keypoints import KeypointRegressor

    terms = correspondence.vertex_terms(anny_model.faces)
    names = [f"fm{k}" for k in terms]
    reg = KeypointRegressor(names, dict(zip(names, terms.values(), strict=True)), {}, anny_model.num_joints)
    g = torch.Generator().manual_seed(0)
    params = anny_model.default_params(3)
    params.joints.copy_(torch.randn(params.joints.shape, generator=g) * 0.2)
    params.expression.copy_(torch.rand(params.expression.shape, generator=g) * 0.5)
    params.transl.copy_(torch.randn(3, 3, generator=g))
    fast = anny_model.posed_points(params, reg)
    out = anny_model(params)
    slow = reg(out.vertices, out.joints)
    assert fast.shape == (3, len(names), 3)
    torch.testing.assert_close(fast, slow, atol=2e-5, rtol=0)
