"""Small rasterizer scenes (dicts of ``rasterize``'s arguments, float64 by default) and a render
with gradients, shared by the rasterizer's tests: ``test_render.py`` checks them against a
brute-force reference, ``test_render_kernels.py`` compares the compiled and torch kernels on them."""

from __future__ import annotations

import math

import torch

from eva_engine.render import RasterConfig, rasterize


def look_camera(width: int, height: int, focal: float, dtype=torch.float64):
    """Camera at the origin looking down +z (OpenCV axes), principal point at the centre."""
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def random_scene(n, width, height, seed=0, dtype=torch.float64, channels=3, spread=0.6, size=(0.03, 0.2)):
    g = torch.Generator().manual_seed(seed)
    viewmat, K = look_camera(width, height, focal=0.9 * max(width, height), dtype=dtype)
    # A slightly rotated/translated camera so viewmat is not the identity.
    angle = 0.2
    rot = torch.tensor(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]],
        dtype=dtype,
    )
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=dtype)
    centre = rot.T @ (torch.tensor([0, 0, 3.0], dtype=dtype) - viewmat[:3, 3])
    scene = dict(
        means=centre
        + spread * torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 0.7, 1.0], dtype=dtype),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=size[0] + (size[1] - size[0]) * torch.rand(n, 3, generator=g, dtype=dtype),
        opacities=0.05 + 0.9 * torch.rand(n, generator=g, dtype=dtype),
        colors=torch.rand(n, channels, generator=g, dtype=dtype),
        viewmat=viewmat,
        K=K,
        width=width,
        height=height,
        background=torch.rand(channels, generator=g, dtype=dtype),
    )
    return scene


def single(
    mean, scale, opacity=0.8, quat=(1.0, 0, 0, 0), width=33, height=25, focal=30.0, color=(0.9, 0.4, 0.1)
):
    """One Gaussian; with the defaults a centred mean projects onto the centre of pixel (16, 12)."""
    viewmat, K = look_camera(width, height, focal)
    return dict(
        means=torch.tensor([mean], dtype=torch.float64),
        quats=torch.tensor([quat], dtype=torch.float64),
        scales=torch.tensor([scale], dtype=torch.float64),
        opacities=torch.tensor([opacity], dtype=torch.float64),
        colors=torch.tensor([color], dtype=torch.float64),
        viewmat=viewmat,
        K=K,
        width=width,
        height=height,
        background=torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64),
    )


def stacked(n: int = 300, size: int = 15) -> dict:
    """``n`` point-like Gaussians (scale 1e-8: the 2D footprint is the eps2d blur) straight ahead of
    the centre pixel of a ``size`` x ``size`` image, opacity 0.5 (so alpha 0.5 there), one behind
    the other 1 cm apart."""
    viewmat, K = look_camera(size, size, 15.0)
    return dict(
        means=torch.stack([torch.zeros(n), torch.zeros(n), 1.0 + 0.01 * torch.arange(n)], -1).double(),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4),
        scales=torch.full((n, 3), 1e-8, dtype=torch.float64),
        opacities=torch.full((n,), 0.5, dtype=torch.float64),
        colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64),
        viewmat=viewmat,
        K=K,
        width=size,
        height=size,
        background=torch.ones(3, dtype=torch.float64),
    )


def cast(scene: dict, dtype) -> dict:
    return {k: (v.to(dtype) if torch.is_tensor(v) else v) for k, v in scene.items()}


PARAMS = ("means", "quats", "scales", "opacities", "colors", "background")


def render_with_grads(scene: dict, config: RasterConfig | None = None, seed: int = 1):
    """Render, backprop a random linear loss of image/alpha/depth; returns (output, grads)."""
    inputs = {k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()}
    out = rasterize(**inputs, config=config)
    g = torch.Generator().manual_seed(seed)
    dt = out.image.dtype
    loss = (
        (out.image * torch.randn(out.image.shape, generator=g, dtype=dt)).sum()
        + (out.alpha * torch.randn(out.alpha.shape, generator=g, dtype=dt)).sum()
        + 0.1 * (out.depth * torch.randn(out.depth.shape, generator=g, dtype=dt)).sum()
    )
    loss.backward()
    return out, {k: inputs[k].grad for k in PARAMS}


def gradcheck_render(scene: dict, config: RasterConfig | None = None) -> bool:
    """``torch.autograd.gradcheck`` of ``rasterize``'s image, alpha and depth with respect to
    every Gaussian parameter and the background (the scene's other entries held fixed)."""
    fixed = {k: v for k, v in scene.items() if k not in PARAMS}

    def fn(*params):
        out = rasterize(**dict(zip(PARAMS, params, strict=True)), **fixed, config=config)
        return out.image, out.alpha, out.depth

    inputs = tuple(scene[k].clone().requires_grad_(True) for k in PARAMS)
    return torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)
