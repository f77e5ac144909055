"""``rasterize_mode="antialiased"`` (gsplat's mode, Mip-Splatting's 2D filter): each opacity times
sqrt(det(cov2d - eps2d I) / det(cov2d)). A Gaussian much wider than a pixel renders as in the
classic mode; one narrower keeps its 2D mass instead of growing to the eps2d blur at full opacity;
values and gradients are finite for degenerate Gaussians, and both kernels agree."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.render import (
    PARAMS,
    cast,
    gradcheck_render,
    look_camera,
    random_scene,
    render_with_grads,
    single,
)

from eva_engine.avatar import AvatarConfig
from eva_engine.render import RasterConfig, rasterize

KERNELS = pytest.mark.parametrize("kernel", ["auto", "torch"])


def test_known_value_of_one_gaussian():
    f, s, z, o = 30.0, 0.01, 2.0, 0.8  # 0.15 px: far under a pixel
    scene = {**single([0.0, 0.0, z], [s, s, s], opacity=o, width=32, height=24, focal=f)}
    out = rasterize(**scene, rasterize_mode="antialiased")
    raw = (f * s / z) ** 2
    var = raw + 0.3
    alpha = o * (raw / var) * math.exp(-0.5 * 0.5 / var)  # sqrt(det ratio) of an isotropic blob
    torch.testing.assert_close(out.alpha[12, 16, 0].item(), alpha, rtol=1e-12, atol=0)


def test_a_sub_pixel_gaussian_keeps_its_mass():
    """Summed alpha over the image: the classic mode draws every sub-pixel Gaussian as the same
    eps2d blob; the antialiased one scales with its area, and a large one is drawn the same."""

    def mass(scale: float, mode: str) -> float:
        scene = single([0.0, 0.0, 2.0], [scale] * 3, opacity=0.9, width=64, height=64, focal=60.0)
        return float(rasterize(**scene, rasterize_mode=mode).alpha.sum())

    small, smaller, large = 0.01, 0.005, 0.3  # 0.3 px, 0.15 px, 9 px
    assert mass(smaller, "classic") / mass(small, "classic") > 0.8
    ratio = mass(smaller, "antialiased") / mass(small, "antialiased")
    assert ratio == pytest.approx(0.25, rel=0.1)  # the area, (0.15 / 0.3)^2, less the 1/255 cut
    expected = 0.9 * 2 * math.pi * (60.0 * small / 2.0) ** 2
    assert mass(small, "antialiased") == pytest.approx(expected, rel=0.05)
    assert mass(large, "antialiased") == pytest.approx(mass(large, "classic"), rel=0.01)


@KERNELS
def test_gradcheck(kernel):
    scene = random_scene(4, 9, 7, seed=2, spread=0.15, size=(0.01, 0.3))
    scene["K"] = look_camera(9, 7, focal=9.0)[1]
    scene["opacities"] = torch.tensor([0.35, 0.5, 0.6, 0.45], dtype=torch.float64)
    assert gradcheck_render({**scene, "rasterize_mode": "antialiased"}, RasterConfig(kernel=kernel))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kernels_agree(dtype):
    scene = cast(
        {**random_scene(60, 40, 30, seed=5, size=(0.002, 0.2)), "rasterize_mode": "antialiased"}, dtype
    )
    outs = {k: render_with_grads(scene, RasterConfig(kernel=k)) for k in ("auto", "torch")}
    (out_c, grads_c), (out_t, grads_t) = outs["auto"], outs["torch"]
    tol = dict(atol=1e-9, rtol=1e-8) if dtype == torch.float64 else dict(atol=2e-4, rtol=2e-4)
    for name in ("image", "alpha", "depth"):
        torch.testing.assert_close(getattr(out_c, name), getattr(out_t, name), msg=name, **tol)
    for name in PARAMS:
        torch.testing.assert_close(grads_c[name], grads_t[name], msg=name, **tol)


@KERNELS
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_gaussians_are_finite(kernel, dtype):
    """A zero-extent Gaussian has compensation 0 (it is not drawn); a needle, a huge one, a zero
    quaternion and one behind the camera give finite values and gradients."""
    scene = random_scene(6, 20, 16, seed=3)
    scene["scales"][0] = 0.0
    scene["scales"][1] = torch.tensor([0.5, 5e-7, 5e-7], dtype=torch.float64)
    scene["scales"][2] = 1e3
    scene["quats"][3] = 0.0
    scene["means"][4] = torch.tensor([0.0, 0.0, -5.0], dtype=torch.float64)
    scene = cast({**scene, "rasterize_mode": "antialiased"}, dtype)
    out, grads = render_with_grads(scene, RasterConfig(kernel=kernel))
    for name in ("image", "alpha", "depth"):
        assert torch.isfinite(getattr(out, name)).all(), name
    for name, grad in grads.items():
        assert torch.isfinite(grad).all(), name
    assert torch.all(grads["colors"][0] == 0)  # compensation 0: no pixel sees it


def test_the_mode_is_checked_and_kept_by_the_avatar_config():
    scene = single([0.0, 0.0, 2.0], [0.1] * 3)
    with pytest.raises(ValueError, match="rasterize_mode"):
        rasterize(**scene, rasterize_mode="mip")
    with pytest.raises(ValueError, match="rasterize_mode"):
        AvatarConfig(rasterize_mode="mip")
    with pytest.raises(ValueError, match="eps2d"):
        AvatarConfig(eps2d=0.0)
    config = AvatarConfig(rasterize_mode="antialiased", eps2d=0.1)
    assert AvatarConfig.from_dict(config.to_dict()) == config
    assert AvatarConfig.from_dict({}).rasterize_mode == "classic"  # avatars saved before it
