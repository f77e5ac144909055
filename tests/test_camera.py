"""Camera helpers: the project's conventions (Y up, subject faces +Z; OpenCV camera axes)."""

import math

import pytest
import torch

from eva_engine.geometry import camera_center, to_camera
from eva_engine.render import intrinsics, look_at, orbit_camera


def _to_camera(viewmat, p):
    return to_camera(torch.tensor([p], dtype=torch.float32), viewmat)[0]


def test_intrinsics_centre_and_fov():
    K = intrinsics(200, 100, 90.0)
    assert K[0, 2] == 100 and K[1, 2] == 50
    assert K[0, 0] == pytest.approx(50.0) and K[1, 1] == pytest.approx(50.0)
    with pytest.raises(ValueError, match="fov"):
        intrinsics(10, 10, 180.0)
    with pytest.raises(ValueError, match="size"):
        intrinsics(0, 10, 40.0)


def test_look_at_axes_follow_opencv():
    view = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0))
    assert torch.allclose(view[:3, :3] @ view[:3, :3].T, torch.eye(3), atol=1e-6)
    assert torch.linalg.det(view[:3, :3]) == pytest.approx(1.0, abs=1e-6)
    assert torch.allclose(_to_camera(view, (0, 0, 0)), torch.tensor([0.0, 0.0, 3.0]), atol=1e-6)
    # Seen from the front, the subject's left (+X) is image right, world up is image up (-y).
    assert _to_camera(view, (1, 0, 0))[0] > 0
    assert _to_camera(view, (0, 1, 0))[1] < 0
    with pytest.raises(ValueError, match="coincide"):
        look_at((1, 2, 3), (1, 2, 3))
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 3, 0), (0, 0, 0))


@pytest.mark.parametrize("yaw, expected", [(0.0, (0, 0, 2)), (90.0, (2, 0, 0)), (180.0, (0, 0, -2))])
def test_orbit_camera_positions(yaw, expected):
    view = orbit_camera(yaw, 0.0, 2.0, target=(0.0, 0.0, 0.0))
    centre = camera_center(view)
    assert torch.allclose(centre, torch.tensor(expected, dtype=torch.float32), atol=1e-5)
    assert torch.allclose(_to_camera(view, (0, 0, 0)), torch.tensor([0.0, 0.0, 2.0]), atol=1e-5)


def test_orbit_camera_pitch_and_bad_values():
    view = orbit_camera(0.0, 30.0, 2.0)
    centre = camera_center(view)
    assert centre[1] == pytest.approx(2.0 * math.sin(math.radians(30)), abs=1e-5)
    for kwargs in ({"pitch_deg": 90.0}, {"distance": 0.0}, {"distance": float("nan")}):
        with pytest.raises(ValueError):
            orbit_camera(**kwargs)


def test_a_scaled_camera_sees_the_same_point_at_the_same_place_in_more_pixels():
    from eva_engine.render.camera import Camera

    K = intrinsics(64, 48, 50.0)
    cam = Camera(K, look_at(torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3)), 64, 48)
    big = cam.scaled(4)
    assert (big.width, big.height) == (256, 192) and torch.equal(big.viewmat, cam.viewmat)
    point = torch.tensor([0.1, -0.2, 0.3, 1.0])

    def pixel(c):
        x = c.K @ (c.viewmat @ point)[:3]
        return x[:2] / x[2]

    torch.testing.assert_close(pixel(big), pixel(cam) * 4)
    assert torch.equal(cam.K, K)  # the original is left alone
    with pytest.raises(ValueError, match="positive"):
        cam.scaled(0)
