"""The person mask as a fitting target (``align.silhouette``): outline sampling, the terms'
behaviour and stability, and a body's girth that keypoints leave free and the outline fits."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import torch

from eva_engine.align.evaluate import targets_from_params
from eva_engine.align.fit import fit_sequence
from eva_engine.align.silhouette import SilhouetteTargets, silhouette_loss, silhouette_vertices
from eva_engine.align.stages import FitConfig, FitStage
from eva_engine.geometry import project_points, to_camera
from eva_engine.render import intrinsics, orbit_camera

SIZE = 128
K = intrinsics(SIZE, SIZE, 40.0)
VIEW = orbit_camera(0.0, 0.0, 1.2, target=(0.0, 0.5, 0.0))  # head and shoulders


def square_mask(frames: int = 1, lo: int = 40, hi: int = 80) -> torch.Tensor:
    m = torch.zeros(frames, SIZE, SIZE)
    m[:, lo:hi, lo:hi] = 1.0
    return m


def body_masks(model, params) -> torch.Tensor:
    """[F, SIZE, SIZE] the posed body's silhouette (its projected triangles filled)."""
    with torch.no_grad():
        v = model(params).vertices
        uv = project_points(to_camera(v, VIEW), K).numpy()
    faces = model.faces.cpu().numpy()
    out = np.zeros((len(uv), SIZE, SIZE), np.uint8)
    for i in range(len(uv)):
        for tri in np.round(uv[i][faces] * 16).astype(np.int32):  # 4 bits of sub-pixel precision
            cv2.fillConvexPoly(out[i], tri, 1, lineType=cv2.LINE_8, shift=4)
    return torch.from_numpy(out.astype(np.float32))


def test_outline_and_distance_of_a_square_mask():
    sil = SilhouetteTargets.from_masks(square_mask(), points=64)
    assert sil.outline.shape == (1, 64, 2) and float(sil.outline_weight.sum()) == 64
    xy = sil.outline[0]
    on_edge = ((xy - 40).abs() < 0.5) | ((xy - 79).abs() < 0.5)
    assert bool(on_edge.any(-1).all())  # every point on the square's boundary
    d = sil.outside_distance[0, 0]
    assert float(d[40:80, 40:80].abs().max()) == 0.0
    assert abs(float(d[60, 90]) - 11.0) < 0.6 and abs(float(d[60, 20]) - 20.0) < 0.6


def test_frames_without_an_outline_contribute_nothing():
    masks = torch.stack([torch.ones(SIZE, SIZE), torch.zeros(SIZE, SIZE), torch.ones(SIZE, SIZE)])
    masks[2, :, :1] = 0.0  # its outline runs along the frame's edge only
    sil = SilhouetteTargets.from_masks(masks, points=32)
    assert float(sil.outline_weight.sum()) == 0.0
    uv = (torch.rand(3, 50, 2) * SIZE).requires_grad_(True)
    loss = silhouette_loss(uv, sil, torch.full((3,), 100.0), 0.1)
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.isfinite(uv.grad).all()


def test_the_loss_is_lowest_on_the_outline_and_pulls_toward_it():
    sil = SilhouetteTargets.from_masks(square_mask(), points=128)
    g = torch.linspace(40, 79, 40)
    filling = torch.stack(torch.meshgrid(g, g, indexing="xy"), -1).reshape(1, -1, 2)
    scale = torch.tensor([100.0])
    aligned = silhouette_loss(filling, sil, scale, 0.1)
    shifted = filling + torch.tensor([8.0, 0.0])
    uv = shifted.clone().requires_grad_(True)
    moved = silhouette_loss(uv, sil, scale, 0.1)
    moved.backward()
    assert float(aligned) < 1e-6 < float(moved.detach())
    outside = shifted[0, :, 0] > 80
    assert bool((uv.grad[0, outside, 0] > 0).all())  # descent moves them back left, into the mask
    assert float(uv.grad[0, :, 1].abs().max()) < float(uv.grad[0, outside, 0].abs().min())


def test_degenerate_points_give_finite_loss_and_gradients():
    sil = SilhouetteTargets.from_masks(square_mask(2), points=64)
    uv = torch.tensor([[[1e9, -1e9], [60.0, 60.0], [0.0, 0.0]], [[60.0, 60.0]] * 3])
    uv = uv.requires_grad_(True)
    loss = silhouette_loss(uv, sil, torch.tensor([1e-3, 1e6]), 0.1)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(uv.grad).all()


def test_vertex_subset_is_fixed_and_spread():
    a, b = silhouette_vertices(13718, 800), silhouette_vertices(13718, 800)
    assert torch.equal(a, b) and len(a.unique()) == 800 and int(a.max()) < 13718
    assert len(silhouette_vertices(100, 800)) == 100


def test_the_silhouette_fits_the_girth_the_keypoints_leave_free(anny_model):
    """A heavier body than the start, every keypoint exact: the joints barely tell the body's
    girth, the outline does."""
    truth = anny_model.default_params(2)
    truth.shape[:, anny_model.shape_names.index("weight")] = 0.95
    masks = body_masks(anny_model, truth)
    start = anny_model.default_params(2)
    targets = dataclasses.replace(targets_from_params(anny_model, truth, K, VIEW), person_masks=masks)
    stage = FitStage("shape", 30, ("shape",), smooth=0.0)

    def outline_error(w_silhouette: float) -> float:
        config = FitConfig(stages=(dataclasses.replace(stage, w_silhouette=w_silhouette),), ik_iterations=5)
        fitted = fit_sequence(anny_model, targets, init=start, config=config).params
        return float((body_masks(anny_model, fitted) - masks).abs().sum())

    before = float((body_masks(anny_model, start) - masks).abs().sum())
    without, with_outline = outline_error(0.0), outline_error(3.0)
    assert without > 0.8 * before
    assert with_outline < 0.5 * without
