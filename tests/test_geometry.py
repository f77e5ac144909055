"""The shared geometry: world -> camera -> pixels agrees with the pinhole model K [R | t] p."""

import pytest
import torch

from eva_engine.geometry import MIN_DEPTH, camera_center, mean_neighbour_distance, project_points, to_camera
from eva_engine.render import orbit_camera


def test_projection_is_the_pinhole_model_with_skew():
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(2, 7, 3, generator=gen, dtype=torch.float64) * 0.3
    views = torch.stack([orbit_camera(yaw, 10.0, 2.5) for yaw in (0.0, 40.0)]).double()
    K = torch.tensor([[300.0, 2.5, 64.0], [0.0, 310.0, 48.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    homogeneous = torch.cat([points, torch.ones(2, 7, 1, dtype=torch.float64)], dim=-1)
    expected = (K @ (views[:, :3, :] @ homogeneous.transpose(1, 2))).transpose(1, 2)
    expected = expected[..., :2] / expected[..., 2:]
    torch.testing.assert_close(project_points(to_camera(points, views), K), expected)
    # One camera for a batch, or a K per frame: the same pixels.
    torch.testing.assert_close(project_points(to_camera(points[0], views[0]), K), expected[0])
    torch.testing.assert_close(project_points(to_camera(points, views), K.expand(2, 3, 3)), expected)


def test_points_at_or_behind_the_camera_stay_finite():
    cam = torch.tensor([[0.1, 0.2, 0.0], [0.1, 0.2, -1.0], [0.1, 0.2, MIN_DEPTH]], dtype=torch.float64)
    uv = project_points(cam, torch.eye(3, dtype=torch.float64))
    assert torch.isfinite(uv).all()
    torch.testing.assert_close(uv[0], uv[2])


def test_camera_center_maps_to_the_origin():
    view = orbit_camera(30.0, 20.0, 2.0, target=(0.1, 0.9, 0.0)).double()
    centre = camera_center(view)[None]
    torch.testing.assert_close(to_camera(centre, view)[0], torch.zeros(3, dtype=torch.float64))


def test_mean_neighbour_distance_is_exact_for_millimetre_neighbours_far_from_the_origin():
    gen = torch.Generator().manual_seed(0)
    points = torch.tensor([1.0, -0.8, 1.5]) + 0.002 * torch.rand(300, 3, generator=gen)
    points = torch.cat([points, points[:5]])  # duplicates: a neighbour at distance 0
    exact = (points.double()[:, None] - points.double()[None]).norm(dim=-1)
    expected = exact.sort(dim=1).values[:, 1:4].mean(dim=1)
    got = mean_neighbour_distance(points, 3)
    assert got.dtype == points.dtype and got.shape == (305,)
    torch.testing.assert_close(got.double(), expected, rtol=1e-6, atol=1e-9)
    assert (got[:5] < got[5:].mean()).all()  # a duplicate's nearest neighbour is its twin


def test_mean_neighbour_distance_of_few_or_bad_points():
    torch.testing.assert_close(mean_neighbour_distance(torch.zeros(1, 3), 3), torch.tensor([0.01]))
    assert mean_neighbour_distance(torch.zeros(0, 3), 3).shape == (0,)
    # k larger than the other points: all of them.
    two = mean_neighbour_distance(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.3, 0.4]]), 3)
    torch.testing.assert_close(two, torch.tensor([0.5, 0.5]))
    for exact in (True, False):
        two = mean_neighbour_distance(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.3, 0.4]]), 3, exact=exact)
        torch.testing.assert_close(two, torch.tensor([0.5, 0.5]))
        with pytest.raises(ValueError, match="finite"):
            mean_neighbour_distance(torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0]]), 1, exact=exact)


def test_the_brute_force_neighbour_distance_is_torch_cdists_to_the_bit():
    """What the Gaussians' initial scales use (``exact=False``): the values every benchmark before
    b9b9fe3 measured, bit for bit, chunks of 2,048 rows included."""
    gen = torch.Generator().manual_seed(1)
    points = torch.tensor([0.1, 0.9, 0.0]) + 0.4 * torch.rand(5000, 3, generator=gen)
    expected = torch.cdist(points, points).topk(4, dim=1, largest=False).values[:, 1:].mean(dim=1)
    assert torch.equal(mean_neighbour_distance(points, 3, exact=False), expected)
