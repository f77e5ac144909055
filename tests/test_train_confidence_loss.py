"""Confidence-aware loss (EVA §3.4): no trivial minimum (E learns high confidence where the
residual is small and μ where it is large), the avatar's weights keep mean 1 on the person,
finite gradients on degenerate inputs, selection through the loss registry and the trainer's
optimizers."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from eva_engine.render import RenderOutput
from eva_engine.train import (
    PHOTOMETRIC_LOSSES,
    AvatarLoss,
    ConfidenceConfig,
    ConfidenceLoss,
    LossConfig,
    TrainConfig,
    with_overrides,
)
from eva_engine.train.confidence import OfficialConfidenceLoss
from eva_engine.train.trainer import make_extra_optimizers

H = W = 16


def inputs(seed: int = 0, requires_grad: bool = True):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(H, W, 3, generator=g).requires_grad_(requires_grad)
    target = torch.rand(H, W, 3, generator=g)
    alpha = torch.ones(H, W, 1)
    depth = torch.full((H, W, 1), 3.0)
    mask = torch.ones(H, W)
    return image, target, alpha, depth, mask


def test_registered_and_selected_by_config():
    assert PHOTOMETRIC_LOSSES["confidence"] is ConfidenceLoss
    loss = AvatarLoss(LossConfig(photometric="confidence", lambda_lpips=0.0))
    assert isinstance(loss.photometric, ConfidenceLoss)
    params = [p for p in loss.parameters() if p.requires_grad]
    assert params, "the feedback network must be trainable"
    assert not list(AvatarLoss(LossConfig(lambda_lpips=0.0)).parameters())


def test_the_fit_term_pushes_confidence_up_where_the_residual_is_small_and_down_where_large():
    loss = ConfidenceLoss()
    a, mu = loss.config.residual_scale, loss.config.mu
    conf = torch.full((2, 2), 3.0, requires_grad=True)
    residual = torch.tensor([[0.001, 0.01], [0.5, 0.9]])
    loss.fit_term(conf, residual, torch.ones(2, 2, dtype=torch.bool)).backward()
    # d/dC (C|r| - a log C) = |r| - a/C: negative (C grows) for |r| < a/C, positive otherwise.
    assert conf.grad[0, 0] < 0 and conf.grad[0, 1] < 0
    assert conf.grad[1, 0] > 0 and conf.grad[1, 1] > 0
    # Its minimiser is a/|r| clamped to [μ, C_max]: never the collapse C = μ everywhere.
    c = torch.linspace(mu + 1e-3, loss.config.max_confidence, 2000)
    for r in (0.02, 0.05):
        best = c[torch.argmin(c * r - a * torch.log(c))]
        assert best == pytest.approx(a / r, rel=0.01)


@pytest.mark.parametrize("downscale", [1, 2])
def test_the_network_learns_where_to_trust_and_does_not_collapse(downscale):
    """Left half: the render matches the frame; right half: a large residual (a misaligned
    region). The image differs between halves, so E can tell them apart (at half resolution
    too: the halves' boundary falls between pooled cells)."""
    torch.manual_seed(0)
    loss = ConfidenceLoss(ConfidenceConfig(hidden=8, downscale=downscale))
    image = torch.zeros(H, W, 3)
    image[:, W // 2 :, 0] = 1.0
    target = image.clone()
    target[:, W // 2 :] += 0.6
    alpha, depth, mask = torch.ones(H, W, 1), torch.full((H, W, 1), 3.0), torch.ones(H, W)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-2)
    # Coarser, E learns slower: the cells on the halves' boundary blend both answers.
    for _ in range(300 if downscale == 1 else 1000):
        opt.zero_grad()
        loss(image, target, alpha, depth, mask).backward()
        opt.step()
    with torch.no_grad():
        conf = loss.confidence(image, depth, alpha)
    left, right = conf[:, : W // 2 - 1].mean(), conf[:, W // 2 + 1 :].mean()
    assert left > 0.7 * loss.config.max_confidence, (left, right)  # trusted: towards C_max
    assert right < loss.config.mu + 0.5, (left, right)  # misaligned: near the floor μ
    assert torch.isfinite(conf).all()


def test_image_weights_have_mean_one_on_the_person_and_one_elsewhere():
    loss = ConfidenceLoss()
    conf = torch.rand(H, W) * 5 + 1
    region = torch.zeros(H, W, dtype=torch.bool)
    region[4:12, 4:12] = True
    w = loss.weights(conf, region)
    assert w[region].mean() == pytest.approx(1.0, rel=1e-5)
    assert torch.all(w[~region] == 1)
    assert not w.requires_grad
    # At initialisation C is uniform: the image term is exactly L1.
    image, target, alpha, depth, mask = inputs(requires_grad=False)
    residual = (image - target).abs().mean(-1)
    fit = loss.fit_term(loss.confidence(image, depth, alpha), residual, mask > 0.5)
    image_term = (loss(image, target, alpha, depth, mask) - fit).detach()
    assert float(image_term) == pytest.approx(float(residual.mean()), rel=1e-5)


def test_the_avatar_cannot_steer_the_confidence():
    """The render gets gradient only through the weighted residual (sign(r) w / (H W 3))."""
    loss = ConfidenceLoss()
    image, target, alpha, depth, mask = inputs()
    loss(image, target, alpha, depth, mask).backward()
    with torch.no_grad():
        conf = loss.confidence(image, depth, alpha)
        w = loss.weights(conf, mask > 0.5)
    expected = torch.sign(image.detach() - target) * w[..., None] / (H * W * 3)
    assert torch.allclose(image.grad, expected, atol=1e-7)


@pytest.mark.parametrize("downscale", [1, 2])
@pytest.mark.parametrize(
    "case", ["zero_residual", "huge_residual", "empty_region", "zero_depth", "huge_depth", "saturated"]
)
def test_degenerate_inputs_give_finite_values_and_gradients(case, downscale):
    loss = ConfidenceLoss(ConfidenceConfig(downscale=downscale))
    image, target, alpha, depth, mask = inputs()
    if case == "zero_residual":
        target = image.detach().clone()
    elif case == "huge_residual":
        target = target + 1e4
    elif case == "empty_region":
        alpha, mask = torch.zeros(H, W, 1), torch.zeros(H, W)
    elif case == "zero_depth":
        depth = torch.zeros(H, W, 1)
    elif case == "huge_depth":
        depth = torch.full((H, W, 1), 1e8)
    elif case == "saturated":
        with torch.no_grad():
            loss.net.head.bias.fill_(1e4)  # E at its bound: C = C_max
    value = loss(image, target, alpha, depth, mask)
    value.backward()
    assert torch.isfinite(value)
    assert torch.isfinite(image.grad).all()
    for p in loss.parameters():
        assert p.grad is None or torch.isfinite(p.grad).all()
    assert loss.last_confidence.min() >= loss.config.mu
    assert loss.last_confidence.max() <= loss.config.max_confidence + 1e-4


@pytest.mark.parametrize("downscale", [1, 2, 3])
def test_confidence_on_the_region_box_equals_the_whole_frame(downscale):
    """E runs only on the person region's box (grown by its reach): the loss, the avatar's
    gradient and E's gradients are those of running it on the whole frame, also with E at a
    reduced resolution (the box snapped to the pooling grid; 40 px is no multiple of 3)."""
    size = 40
    g = torch.Generator().manual_seed(3)
    loss = ConfidenceLoss(ConfidenceConfig(downscale=downscale))
    with torch.no_grad():
        for p in loss.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    image = torch.rand(size, size, 3, generator=g)
    target = torch.rand(size, size, 3, generator=g)
    alpha, mask = torch.zeros(size, size, 1), torch.zeros(size, size)
    alpha[10:25, 12:30] = 0.9
    mask[8:20, 15:33] = 1.0
    depth = alpha * 2.5
    full = ConfidenceLoss(loss.config)
    full.load_state_dict(loss.state_dict())
    full.confidence_on_region = lambda image, depth, alpha, region: full.confidence(image, depth, alpha)
    values, grads = [], []
    for fn in (loss, full):
        img = image.clone().requires_grad_(True)
        value = fn(img, target, alpha, depth, mask)
        value.backward()
        values.append(value.detach())
        grads.append([img.grad, *[p.grad for p in fn.parameters()]])
    assert torch.allclose(values[0], values[1], atol=1e-6)
    for a, b in zip(*grads, strict=True):
        assert torch.allclose(a, b, atol=1e-6)
    region = (mask > 0.5) | (alpha[..., 0] > 0.5)
    assert torch.allclose(loss.last_confidence[region], full.last_confidence[region], atol=1e-6)


def test_invalid_config_is_refused():
    with pytest.raises(ValueError, match="mu"):
        ConfidenceLoss(ConfidenceConfig(mu=2.0, max_confidence=1.5))
    with pytest.raises(ValueError, match="downscale"):
        ConfidenceLoss(ConfidenceConfig(downscale=0))


def test_the_loss_config_carries_the_networks_settings():
    config = with_overrides(
        TrainConfig(loss=LossConfig(photometric="confidence", lambda_lpips=0.0)),
        ["loss.confidence.downscale=2", "loss.confidence.hidden=8"],
    )
    loss = AvatarLoss(config.loss)
    assert loss.photometric.config == ConfidenceConfig(hidden=8, downscale=2)
    assert loss.photometric.net.head.in_channels == 8


@pytest.mark.parametrize("shape", [(15, 17), (1, 1), (2, 33)])
def test_reduced_resolution_confidence_keeps_the_frames_shape_and_bounds(shape):
    """E at half resolution on frames of odd sizes (edge-padded to the pooling grid, cut back
    after the upsampling): C has the frame's shape and stays within [μ, C_max]."""
    h, w = shape
    g = torch.Generator().manual_seed(5)
    loss = ConfidenceLoss(ConfidenceConfig(downscale=2))
    with torch.no_grad():
        for p in loss.parameters():
            p.copy_(torch.randn(p.shape, generator=g))
    image = torch.rand(h, w, 3, generator=g, requires_grad=True)
    alpha = torch.ones(h, w, 1)
    conf = loss.confidence(image, alpha * 3.0, alpha)
    assert conf.shape == (h, w)
    assert conf.min() >= loss.config.mu and conf.max() <= loss.config.max_confidence + 1e-4
    value = loss(image, torch.rand(h, w, 3, generator=g), alpha, alpha * 3.0, torch.ones(h, w))
    value.backward()
    assert torch.isfinite(image.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in loss.parameters())


def test_trainer_optimises_the_network():
    avatar_loss = AvatarLoss(LossConfig(photometric="confidence", lambda_lpips=0.0))
    no_mlps = SimpleNamespace(networks=lambda: {})  # only the loss's parameters here
    extra = make_extra_optimizers(no_mlps, TrainConfig(), avatar_loss)
    held = {id(p) for opt in extra for group in opt.param_groups for p in group["params"]}
    assert held == {id(p) for p in avatar_loss.photometric.parameters()}


def test_render_output_inputs_work_through_avatar_loss():
    image, target, alpha, depth, mask = inputs()
    n = 3
    radii = torch.ones(n, dtype=torch.int32)
    render = RenderOutput(image, alpha, depth, torch.zeros(n, 2), radii, torch.ones(n), 0)
    terms = AvatarLoss(LossConfig(photometric="confidence", lambda_lpips=0.0))(render, target, mask)
    terms["total"].backward()
    assert torch.isfinite(terms["total"]) and torch.isfinite(image.grad).all()


# -- the official code's form ---------------------------------------------------------------
def test_official_form_is_the_authors_confidence():
    """C = (1 + exp(E)) / 2 with E = conv2([x, leaky_relu(conv1(x), 0.2)]) of x = [I_r, D_r]
    (1x1 convolutions), the term mean(C |r|) with no log term, Kaiming-normal x 0.1 weights."""
    assert PHOTOMETRIC_LOSSES["confidence_official"] is OfficialConfidenceLoss
    loss = OfficialConfidenceLoss(generator=torch.Generator().manual_seed(3))
    net = loss.net
    assert torch.all(net.conv1.bias == 0) and torch.all(net.conv2.bias == 0)
    # Kaiming normal (fan_in 4 and 7, gain sqrt 2) x 0.1: std 0.1 * sqrt(2 / fan_in).
    assert float(net.conv1.weight.detach().abs().max()) < 0.1 * math.sqrt(2 / 4) * 5
    image, target, alpha, depth, mask = inputs(1)
    value = loss(image, target, alpha, depth, mask).detach()
    image = image.detach()
    x = torch.cat([image, depth], dim=-1).reshape(-1, 4)
    w1, w2 = net.conv1.weight[:, :, 0, 0], net.conv2.weight[:, :, 0, 0]
    hidden = torch.nn.functional.leaky_relu(x @ w1.T + net.conv1.bias, 0.2)
    e = (torch.cat([x, hidden], dim=-1) @ w2.T + net.conv2.bias).reshape(H, W)
    conf = ((1 + torch.exp(e)) / 2).detach()
    assert loss.last_confidence == pytest.approx(conf, rel=1e-5)
    assert float(value) == pytest.approx(float(((image - target).abs() * conf[..., None]).mean()), rel=1e-5)
    # Zero weights: C = 1 (plain L1); the floor is 0.5, where E -> -inf.
    loss.requires_grad_(False)
    with torch.no_grad():
        net.conv2.weight.zero_()
    assert float(loss(image, target, alpha, depth, mask)) == pytest.approx(
        float((image - target).abs().mean())
    )
    with torch.no_grad():
        net.conv2.bias.fill_(-50.0)
    assert float(loss(image, target, alpha, depth, mask)) == pytest.approx(
        0.5 * float((image - target).abs().mean()), rel=1e-5
    )


def test_official_form_passes_gradient_to_the_render_through_the_confidence():
    loss = OfficialConfidenceLoss()
    image, target, alpha, depth, mask = inputs(2)
    depth = depth.clone().requires_grad_(True)
    loss(image, target, alpha, depth, mask).backward()
    assert depth.grad is not None and float(depth.grad.abs().sum()) > 0  # depth only acts through C
    plain = image.detach().clone().requires_grad_(True)
    conf = loss.last_confidence
    ((plain - target).abs() * conf[..., None]).mean().backward()
    assert not torch.allclose(image.grad, plain.grad)  # C's own gradient reaches the image
    # Its network learns by lowering C (nothing stops it: the official code's choice).
    loss = OfficialConfidenceLoss()
    opt = torch.optim.Adam(loss.parameters(), lr=1e-2)
    image, target, alpha, depth, mask = inputs(3, requires_grad=False)
    first = float(loss(image, target, alpha, depth, mask).detach())
    for _ in range(50):
        opt.zero_grad()
        loss(image, target, alpha, depth, mask).backward()
        opt.step()
    last = float(loss(image, target, alpha, depth, mask).detach())
    assert float(loss.last_confidence.mean()) < 1.0 and last < first


@pytest.mark.parametrize("case", ["huge_depth", "zero_image", "saturated"])
def test_official_form_degenerate_inputs_stay_finite(case):
    loss = OfficialConfidenceLoss()
    image, target, alpha, depth, mask = inputs(4)
    if case == "huge_depth":
        depth = torch.full((H, W, 1), 1e6)
    elif case == "zero_image":
        image = torch.zeros(H, W, 3, requires_grad=True)
    else:
        with torch.no_grad():
            loss.net.conv2.bias.fill_(1e4)  # exp would overflow without the cap
    value = loss(image, target, alpha, depth, mask)
    value.backward()
    assert math.isfinite(float(value.detach())) and torch.isfinite(image.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in loss.parameters())
