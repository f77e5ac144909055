"""Spherical-harmonics colours: constants, conventions and helpers."""

import math

import pytest
import torch

from eva_engine.geometry import camera_center
from eva_engine.render import eval_sh, num_sh_bases, rgb_to_sh, sh_basis, view_dirs
from eva_engine.render.sh import SH_C0, SH_C1


def _unit_dirs(n: int, seed: int = 0) -> torch.Tensor:
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


def test_degree0_is_dc_formula():
    coeffs = torch.randn(10, 1, 3, dtype=torch.float64)
    out = eval_sh(0, coeffs, _unit_dirs(10))
    torch.testing.assert_close(out, torch.clamp_min(SH_C0 * coeffs[:, 0] + 0.5, 0.0))
    assert SH_C0 == pytest.approx(0.5 / math.sqrt(math.pi))


def test_rgb_to_sh_round_trip():
    rgb = torch.rand(7, 3, dtype=torch.float64)
    torch.testing.assert_close(eval_sh(0, rgb_to_sh(rgb)[:, None, :], _unit_dirs(7)), rgb)


def test_degree1_known_values():
    # 3DGS order: Y_1 = (-C1 y, C1 z, -C1 x).
    coeffs = torch.zeros(3, 4, 3, dtype=torch.float64)
    coeffs[:, 1:4, 0] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    dirs = torch.eye(3, dtype=torch.float64)  # +x, +y, +z
    out = eval_sh(1, coeffs, dirs * 5.0)  # any length: directions are normalised
    expect = 0.5 + SH_C1 * torch.tensor([-3.0, -1.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(out[:, 0], expect.clamp_min(0))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_addition_theorem(degree):
    # For real orthonormal SH, sum_m Y_lm(d)^2 = (2l + 1) / (4 pi) for every unit d: checks every
    # constant up to sign.
    basis = sh_basis(degree, _unit_dirs(50))
    assert basis.shape == (50, num_sh_bases(degree))
    for band in range(degree + 1):
        sq = basis[:, band**2 : (band + 1) ** 2].pow(2).sum(-1)
        torch.testing.assert_close(sq, torch.full_like(sq, (2 * band + 1) / (4 * math.pi)))


def test_orthonormal_on_the_sphere():
    d = _unit_dirs(400_000, seed=3)
    basis = sh_basis(3, d)
    gram = basis.T @ basis * (4 * math.pi / d.shape[0])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.02, rtol=0)


def test_extra_coefficients_ignored_and_too_few_rejected():
    coeffs = torch.randn(5, 16, 3, dtype=torch.float64)
    d = _unit_dirs(5)
    torch.testing.assert_close(eval_sh(1, coeffs, d), eval_sh(1, coeffs[:, :4], d))
    with pytest.raises(ValueError):
        eval_sh(2, coeffs[:, :4], d)
    with pytest.raises(ValueError):
        sh_basis(4, d)


def test_eval_sh_gradients_finite_for_zero_direction():
    coeffs = torch.randn(2, 16, 3, dtype=torch.float64, requires_grad=True)
    dirs = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0]], dtype=torch.float64, requires_grad=True)
    eval_sh(3, coeffs, dirs).sum().backward()
    assert torch.isfinite(coeffs.grad).all() and torch.isfinite(dirs.grad).all()


def test_camera_center_and_view_dirs():
    angle = 0.3
    rot = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]],
        dtype=torch.float64,
    )
    centre = torch.tensor([1.0, 2.0, -3.0], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ centre
    torch.testing.assert_close(camera_center(viewmat), centre)
    means = torch.randn(4, 3, dtype=torch.float64)
    torch.testing.assert_close(view_dirs(means, viewmat), means - centre)
