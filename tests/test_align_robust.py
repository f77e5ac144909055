"""The robust terms of the fitting objective: values and gradients on constructed inputs."""

import pytest
import torch

from eva_engine.align.robust import geman_mcclure, weighted_gm, z_only_gm


def test_geman_mcclure_values_and_limits():
    r = torch.tensor([0.0, 0.01, 1.0, 1e6], dtype=torch.float64)
    sigma = 1.0
    assert torch.allclose(geman_mcclure(r, sigma), r**2 / (1 + r**2))
    assert geman_mcclure(r, 0.1)[1] == pytest.approx(0.01**2, rel=1e-2)  # quadratic near 0
    assert geman_mcclure(r, 0.1)[-1] == pytest.approx(0.01, rel=1e-6)  # bounded by sigma^2
    with pytest.raises(ValueError):
        geman_mcclure(r, 0.0)


def test_geman_mcclure_gradient_matches_closed_form_and_vanishes_for_outliers():
    r = torch.tensor([-3.0, -0.2, 0.0, 0.5, 50.0], dtype=torch.float64, requires_grad=True)
    sigma = 0.7
    geman_mcclure(r, sigma).sum().backward()
    expected = 2 * r.detach() * sigma**4 / (sigma**2 + r.detach() ** 2) ** 2
    assert torch.allclose(r.grad, expected)
    assert abs(r.grad[-1]) < 1e-4 * abs(r.grad[3])
    assert torch.autograd.gradcheck(lambda x: geman_mcclure(x, sigma), (r.detach().clone().requires_grad_(),))


def test_weighted_gm_ignores_zero_weight_and_is_finite_with_no_weight():
    residual = torch.tensor([[[0.1, 0.0], [1e9, float("1e9")]]], requires_grad=True)
    weights = torch.tensor([[1.0, 0.0]])
    loss = weighted_gm(residual, weights, 1.0)
    assert loss.item() == pytest.approx(0.01 / 1.01, rel=1e-5)
    loss.backward()
    assert torch.isfinite(residual.grad).all() and residual.grad[0, 1].abs().sum() == 0
    none = weighted_gm(residual, torch.zeros(1, 2), 1.0)
    assert none.item() == 0.0
    none.backward()
    assert torch.isfinite(residual.grad).all()


def test_z_only_term_sees_relative_depth_only():
    target = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 2.05], [0.2, 0.0, 1.9]])
    # Same relative depths, other x/y and a different absolute depth: zero loss.
    model = target.clone()
    model[:, :2] += torch.tensor([5.0, -3.0])
    model[:, 2] += 0.7
    w = torch.ones(3)
    assert z_only_gm(model, target, w, 0.05).item() == pytest.approx(0.0, abs=1e-12)
    # One finger point 3 cm too deep relative to the wrist: psi(0.03) / total weight.
    model[2, 2] += 0.03
    model.requires_grad_(True)
    loss = z_only_gm(model, target, w, 0.05)
    s2 = 0.05**2
    assert loss.item() == pytest.approx(s2 * 0.03**2 / (s2 + 0.03**2) / 3, rel=1e-4)
    loss.backward()
    assert model.grad[:, :2].abs().sum() == 0  # x and y get no gradient
    assert model.grad[2, 2] > 0 and model.grad[0, 2] < 0  # wrist is the reference
