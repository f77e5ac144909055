"""eva_engine.render.rasterize against a brute-force reference, its gradients and hard cases.

The reference below is written independently of the module: float64, every Gaussian for every
pixel, one Gaussian at a time in depth order, exactly the 3DGS per-pixel loop. The default
configuration runs the compiled kernels where they build; the main checks also run the torch
kernels explicitly (test_render_kernels.py compares the two everywhere).
"""

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
    stacked,
)

from eva_engine.render import (
    CompositeConfig,
    RasterConfig,
    bin_gaussians,
    eval_sh,
    project_gaussians,
    rasterize,
    view_dirs,
)

# ----------------------------------------------------------------------------- reference


def _rotmat(q: torch.Tensor) -> torch.Tensor:
    n = q.norm(dim=-1, keepdim=True)
    q = torch.where(n > 1e-12, q / n.clamp_min(1e-300), torch.tensor([1.0, 0, 0, 0], dtype=q.dtype))
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def render_reference(scene: dict, near: float = 0.01, far: float = 1e10, eps2d: float = 0.3, stats=None):
    """Brute force in float64: returns image [H, W, D], alpha [H, W, 1], depth [H, W, 1].

    ``stats`` (a dict), if given, receives "stopped": [H, W] pixels that hit the T <= 1e-4 stop.
    """
    d64 = {k: (v.detach().double() if torch.is_tensor(v) else v) for k, v in scene.items()}
    W, H = d64["width"], d64["height"]
    vm, K = d64["viewmat"], d64["K"]
    fx, fy, cx, cy = K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item()
    colors = d64["colors"]
    bg = d64.get("background")
    p = d64["means"] @ vm[:3, :3].T + vm[:3, 3]
    cov3 = (
        _rotmat(d64["quats"]) @ torch.diag_embed(d64["scales"] ** 2) @ _rotmat(d64["quats"]).transpose(1, 2)
    )
    covc = vm[:3, :3] @ cov3 @ vm[:3, :3].T

    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    px, py = xs + 0.5, ys + 0.5
    T = torch.ones(H, W, dtype=torch.float64)
    img = torch.zeros(H, W, colors.shape[1], dtype=torch.float64)
    dep = torch.zeros(H, W, dtype=torch.float64)
    done = torch.zeros(H, W, dtype=torch.bool)
    order = sorted(range(p.shape[0]), key=lambda i: (p[i, 2].item(), i))
    for i in order:
        x, y, z = p[i].tolist()
        if not (near <= z <= far):
            continue
        limx_p = (W - cx) / fx + 0.3 * 0.5 * W / fx
        limx_n = cx / fx + 0.3 * 0.5 * W / fx
        limy_p = (H - cy) / fy + 0.3 * 0.5 * H / fy
        limy_n = cy / fy + 0.3 * 0.5 * H / fy
        tx = z * min(limx_p, max(-limx_n, x / z))
        ty = z * min(limy_p, max(-limy_n, y / z))
        J = torch.tensor([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]], dtype=torch.float64)
        cov2 = J @ covc[i] @ J.T + eps2d * torch.eye(2, dtype=torch.float64)
        det = (cov2[0, 0] * cov2[1, 1] - cov2[0, 1] ** 2).item()
        if det <= 0:
            continue
        mx, my = fx * x / z + cx, fy * y / z + cy
        rx, ry = math.ceil(3.33 * math.sqrt(cov2[0, 0])), math.ceil(3.33 * math.sqrt(cov2[1, 1]))
        if mx + rx <= 0 or mx - rx >= W or my + ry <= 0 or my - ry >= H:
            continue
        conic = torch.linalg.inv(cov2)
        dx, dy = mx - px, my - py
        power = -0.5 * (conic[0, 0] * dx * dx + conic[1, 1] * dy * dy) - conic[0, 1] * dx * dy
        alpha = (d64["opacities"][i] * torch.exp(power)).clamp(max=0.999)
        live = (alpha >= 1 / 255) & ~done
        t_next = T * (1 - alpha)
        stop = live & (t_next <= 1e-4)
        use = live & ~stop
        done |= stop
        w = torch.where(use, alpha * T, torch.zeros_like(T))
        img += w[..., None] * colors[i]
        dep += w * z
        T = torch.where(use, t_next, T)
    if bg is not None:
        img = img + T[..., None] * bg
    if stats is not None:
        stats["stopped"] = done
    return img, (1 - T)[..., None], dep[..., None]


def assert_finite(out, grads):
    for name in ("image", "alpha", "depth", "means2d"):
        assert torch.isfinite(getattr(out, name)).all(), name
    for name, grad in grads.items():
        assert grad is not None and torch.isfinite(grad).all(), name


# ----------------------------------------------------------------------------- forward vs reference


@pytest.mark.parametrize(
    ("n", "width", "height", "seed"),
    [(1, 16, 16, 0), (12, 8, 8, 1), (40, 37, 23, 2), (80, 64, 48, 3), (150, 100, 17, 4), (60, 5, 70, 5)],
)
def test_matches_brute_force_reference(n, width, height, seed):
    scene = random_scene(n, width, height, seed)
    ref_img, ref_alpha, ref_depth = render_reference(scene)
    for config in (RasterConfig(), RasterConfig(kernel="torch"), RasterConfig(backend="autograd")):
        out = rasterize(**scene, config=config)
        assert out.image.shape == (height, width, 3)
        assert out.alpha.shape == out.depth.shape == (height, width, 1)
        torch.testing.assert_close(out.image, ref_img, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.alpha, ref_alpha, rtol=0, atol=1e-10)
        torch.testing.assert_close(out.depth, ref_depth, rtol=0, atol=1e-9)
    assert ref_alpha.max() > 0.1, "scene should cover part of the image"


def test_reference_scene_exercises_termination_and_float32():
    # Dense, opaque scene: many pixels stop early. float32 agrees with the float64 reference except
    # possibly at the odd pixel where a threshold decision flips by rounding.
    scene = random_scene(300, 48, 40, seed=7, spread=0.3, size=(0.05, 0.2))
    scene["opacities"] = 0.6 + 0.39 * torch.rand(
        300, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    stats = {}
    ref_img, _, _ = render_reference(scene, stats=stats)
    assert stats["stopped"].float().mean() > 0.1  # pixels that hit the T <= 1e-4 stop
    out64 = rasterize(**scene)
    torch.testing.assert_close(out64.image, ref_img, rtol=0, atol=1e-10)
    out32 = rasterize(**cast(scene, torch.float32))
    err = (out32.image.double() - ref_img).abs()
    assert (err < 1e-4).float().mean() > 0.995
    assert err.mean() < 1e-5


@pytest.mark.parametrize("channels", [1, 5])
def test_any_number_of_channels(channels):
    scene = random_scene(30, 24, 20, seed=11, channels=channels)
    out = rasterize(**scene)
    assert out.image.shape == (20, 24, channels)
    torch.testing.assert_close(out.image, render_reference(scene)[0], rtol=0, atol=1e-10)


@pytest.mark.parametrize("chunk,block", [(1, 64), (3, 200), (32, 1 << 19), (64, 4096)])
def test_result_independent_of_work_partition(chunk, block):
    scene = random_scene(120, 40, 30, seed=5, spread=0.35)
    base_out, base_grads = render_with_grads(scene)
    cfg = RasterConfig(composite=CompositeConfig(chunk_size=chunk, block_elements=block))
    out, grads = render_with_grads(scene, cfg)
    torch.testing.assert_close(out.image, base_out.image, rtol=0, atol=1e-12)
    for k in PARAMS:
        torch.testing.assert_close(grads[k], base_grads[k], rtol=1e-9, atol=1e-11)


def test_tile_size_16_matches():
    scene = random_scene(50, 45, 33, seed=9)
    out = rasterize(**scene, config=RasterConfig(tile_size=16))  # partial 16x16 tiles on both axes
    torch.testing.assert_close(out.image, render_reference(scene)[0], rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_tile_test_drops_only_invisible_pairs(dtype):
    # Thin, tilted, faint and large Gaussians: the bounding box over-covers tiles a lot.
    scene = cast(random_scene(150, 61, 45, seed=13, size=(0.005, 0.3)), dtype)
    proj = project_gaussians(
        *(scene[k] for k in ("means", "quats", "scales", "viewmat", "K", "width", "height"))
    )
    box = bin_gaussians(proj.means2d, proj.radii, proj.depths, 61, 45, 8)
    exact = bin_gaussians(proj.means2d, proj.radii, proj.depths, 61, 45, 8, proj.conics, scene["opacities"])
    assert exact.num_intersections < 0.9 * box.num_intersections

    # Brute force: max alpha over each box pair's in-image pixel centres.
    g, t = box.gauss_ids, box.tile_ids
    r = torch.arange(8, dtype=torch.float64) + 0.5
    px = (t % box.tiles_x * 8)[:, None].double() + r  # [M, 8]
    py = (t // box.tiles_x * 8)[:, None].double() + r
    m, (a, b, c) = proj.means2d[g].double(), proj.conics[g].double().unbind(-1)
    dx = (m[:, 0, None] - px)[:, None, :]  # [M, 1, 8]
    dy = (m[:, 1, None] - py)[:, :, None]  # [M, 8, 1]
    q = a[:, None, None] * dx**2 + 2 * b[:, None, None] * dx * dy + c[:, None, None] * dy**2
    alpha = scene["opacities"][g].double()[:, None, None] * torch.exp(-0.5 * q)
    alpha = alpha.masked_fill((px >= 61)[:, None, :] | (py >= 45)[:, :, None], 0)
    visible = alpha.amax(dim=(1, 2)) >= 1 / 255
    kept = set(zip(exact.gauss_ids.tolist(), exact.tile_ids.tolist(), strict=True))
    for gi, ti in zip(g[visible].tolist(), t[visible].tolist(), strict=True):
        assert (gi, ti) in kept


# ----------------------------------------------------------------------------- gradients


KERNELS = pytest.mark.parametrize("kernel", ["auto", "torch"])


@KERNELS
@pytest.mark.parametrize(("n", "width", "height", "seed"), [(25, 30, 20, 0), (200, 40, 36, 1)])
def test_hand_written_backward_matches_autograd(n, width, height, seed, kernel):
    scene = random_scene(n, width, height, seed, spread=0.4)
    out_t, grads_t = render_with_grads(scene, RasterConfig(backend="tiled", kernel=kernel))
    out_a, grads_a = render_with_grads(scene, RasterConfig(backend="autograd"))
    for k in PARAMS:
        torch.testing.assert_close(grads_t[k], grads_a[k], rtol=1e-8, atol=1e-10, msg=k)
    torch.testing.assert_close(out_t.means2d.grad, out_a.means2d.grad, rtol=1e-8, atol=1e-10)


@KERNELS
def test_hand_written_backward_matches_autograd_with_clamped_alphas(kernel):
    # Opacity 1 saturates alpha at 0.999 near the centres (zero gradient there), and the dense
    # stack makes pixels stop early: both switches must agree between the two backwards.
    scene = random_scene(120, 40, 32, seed=6, spread=0.3, size=(0.3, 0.6))
    scene["opacities"][::3] = 1.0
    proj = project_gaussians(
        *(scene[k] for k in ("means", "quats", "scales", "viewmat", "K", "width", "height"))
    )
    ys, xs = torch.meshgrid(torch.arange(32.0), torch.arange(40.0), indexing="ij")
    d = proj.means2d[::3, None, None, :] - torch.stack([xs + 0.5, ys + 0.5], -1).double()
    a, b, c = proj.conics[::3, None, None].unbind(-1)
    raw = torch.exp(-0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) - b * d[..., 0] * d[..., 1])
    assert ((raw > 0.999) & (proj.depths[::3, None, None] > 0)).sum() >= 3  # some clamped pairs
    _, grads_t = render_with_grads(scene, RasterConfig(backend="tiled", kernel=kernel))
    _, grads_a = render_with_grads(scene, RasterConfig(backend="autograd"))
    for k in PARAMS:
        torch.testing.assert_close(grads_t[k], grads_a[k], rtol=1e-8, atol=1e-10, msg=k)


@KERNELS
def test_hand_written_backward_matches_autograd_float32(kernel):
    scene = cast(random_scene(150, 48, 40, seed=3, spread=0.4), torch.float32)
    _, grads_t = render_with_grads(scene, RasterConfig(backend="tiled", kernel=kernel))
    _, grads_a = render_with_grads(scene, RasterConfig(backend="autograd"))
    for k in PARAMS:
        scale = grads_a[k].abs().max()
        assert (grads_t[k] - grads_a[k]).abs().max() <= 1e-4 * scale, k


def _smooth_scene():
    """Tiny scene whose alphas stay clear of the 1/255, 0.999 and T = 1e-4 switches."""
    scene = random_scene(4, 12, 10, seed=2, spread=0.15, size=(0.15, 0.3))
    scene["opacities"] = torch.tensor([0.35, 0.5, 0.6, 0.45], dtype=torch.float64)
    return scene


@KERNELS
def test_gradients_match_finite_differences(kernel):
    scene = _smooth_scene()
    config = RasterConfig(kernel=kernel)
    _, grads = render_with_grads(scene, config)

    def loss_of(s):
        out = rasterize(**s, config=config)
        g = torch.Generator().manual_seed(1)
        dt = torch.float64
        return (
            (out.image * torch.randn(out.image.shape, generator=g, dtype=dt)).sum()
            + (out.alpha * torch.randn(out.alpha.shape, generator=g, dtype=dt)).sum()
            + 0.1 * (out.depth * torch.randn(out.depth.shape, generator=g, dtype=dt)).sum()
        ).item()

    def nudged(name, i, delta):
        t = scene[name].clone()
        t.view(-1)[i] += delta
        return {**scene, name: t}

    eps = 1e-6
    for name in PARAMS:
        numeric = torch.zeros_like(scene[name])
        for i in range(scene[name].numel()):
            numeric.view(-1)[i] = (loss_of(nudged(name, i, eps)) - loss_of(nudged(name, i, -eps))) / (2 * eps)
        torch.testing.assert_close(grads[name], numeric, rtol=1e-5, atol=1e-6, msg=name)


@KERNELS
def test_gradcheck_tiled(kernel):
    scene = _smooth_scene()
    scene["width"], scene["height"] = 9, 7
    scene["K"] = look_camera(9, 7, focal=9.0)[1]
    assert gradcheck_render(scene, RasterConfig(kernel=kernel))


def test_means2d_grad_is_populated():
    scene = random_scene(30, 32, 24, seed=4)
    scene["means"][0] = torch.tensor([0.0, 0.0, -5.0], dtype=torch.float64)  # culled: behind the camera
    out, _ = render_with_grads(scene)
    g = out.means2d.grad
    assert g is not None and g.shape == (30, 2)
    assert torch.all(g[0] == 0) and out.radii[0] == 0
    visible = out.radii > 0
    assert (g[visible].abs().sum(-1) > 0).float().mean() > 0.9


def test_means2d_grad_is_in_pixels():
    # L = sum_p alpha_p x_p. Integrating by parts over the region D where alpha >= 1/255 (the
    # jump at its edge has no gradient): dL/dmeans2d.x = sum_D alpha - |D| / 255, in pixels.
    scene = single([0.0, 0.0, 2.0], [0.2, 0.2, 0.2], opacity=0.6, width=41, height=41, focal=40.0)
    scene["means"].requires_grad_(True)
    out = rasterize(**scene)
    xs = torch.arange(41, dtype=torch.float64) + 0.5
    (out.alpha[..., 0] * xs).sum().backward()
    g = out.means2d.grad[0]
    area = (out.alpha > 0).sum().item()
    torch.testing.assert_close(g[0].item(), out.alpha.sum().item() - area / 255, rtol=5e-3, atol=0)
    assert abs(g[1].item()) < 1e-6 * abs(g[0].item())


# ----------------------------------------------------------------------------- hard cases


def _check_against_reference(scene, atol=1e-10):
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    ref_img, ref_alpha, ref_depth = render_reference(scene)
    torch.testing.assert_close(out.image, ref_img, rtol=0, atol=atol)
    torch.testing.assert_close(out.alpha, ref_alpha, rtol=0, atol=atol)
    torch.testing.assert_close(out.depth, ref_depth, rtol=0, atol=10 * atol)
    return out, grads


@KERNELS
def test_no_gaussians(kernel):
    viewmat, K = look_camera(20, 12, 20.0)
    bg = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
    empty = torch.zeros(0, 3, dtype=torch.float64, requires_grad=True)
    out = rasterize(
        empty,
        torch.zeros(0, 4, dtype=torch.float64),
        torch.zeros(0, 3, dtype=torch.float64),
        torch.zeros(0, dtype=torch.float64),
        torch.zeros(0, 3, dtype=torch.float64),
        viewmat,
        K,
        20,
        12,
        background=bg,
        config=RasterConfig(kernel=kernel),
    )
    assert torch.equal(out.image, bg.detach().expand(12, 20, 3))
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0)
    assert out.radii.shape == (0,) and out.means2d.shape == (0, 2)
    out.image.sum().backward()
    torch.testing.assert_close(bg.grad, torch.full((3,), 240.0, dtype=torch.float64))


@KERNELS
@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "colors"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_a_non_finite_gaussian_is_not_drawn(field, value, kernel):
    """A Gaussian with NaN or inf anywhere renders as if it were absent, its gradients are zero,
    and the others' are those of the scene without it."""
    scene = random_scene(6, 24, 20, seed=3)
    bad = dict(scene)
    bad[field] = scene[field].clone()
    bad[field][2] = value
    without = {k: (v[[0, 1, 3, 4, 5]] if k in PARAMS and k != "background" else v) for k, v in scene.items()}
    config = RasterConfig(kernel=kernel)
    out, grads = render_with_grads(bad, config)
    ref, ref_grads = render_with_grads(without, config)
    assert_finite(out, grads)
    for name in ("image", "alpha", "depth"):
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), rtol=1e-10, atol=1e-12)
    for k in PARAMS:
        if k == "background":
            torch.testing.assert_close(grads[k], ref_grads[k])
            continue
        assert torch.all(grads[k][2] == 0), k
        torch.testing.assert_close(grads[k][[0, 1, 3, 4, 5]], ref_grads[k], rtol=1e-10, atol=1e-12, msg=k)


def test_single_gaussian_known_value():
    # Isotropic Gaussian straight ahead: 2D sigma^2 = (f s / z)^2 + eps2d at the image centre.
    f, s, z, o = 30.0, 0.1, 2.0, 0.8
    scene = single([0.0, 0.0, z], [s, s, s], opacity=o, width=32, height=24, focal=f)
    out, _ = _check_against_reference(scene)
    var = (f * s / z) ** 2 + 0.3
    d2 = 0.5**2 + 0.5**2  # pixel (16, 12) has its centre half a pixel off the projected mean
    alpha = o * math.exp(-0.5 * d2 / var)
    torch.testing.assert_close(out.alpha[12, 16, 0].item(), alpha, rtol=1e-12, atol=0)
    expect = alpha * torch.tensor([0.9, 0.4, 0.1]) + (1 - alpha) * torch.tensor([0.2, 0.3, 0.4])
    torch.testing.assert_close(out.image[12, 16].float(), expect, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(out.depth[12, 16, 0].item(), alpha * z, rtol=1e-12, atol=0)
    assert out.radii[0] == math.ceil(3.33 * math.sqrt(var))


def test_behind_camera_and_near_plane():
    scene = random_scene(6, 24, 18, seed=1)
    scene["means"] = torch.tensor(
        [[0, 0, -1.0], [0.1, 0, -0.001], [0.0, 0.0, 0.005], [0.0, 0.05, 0.011], [0.02, 0, 0.03], [0, 0, 1.0]],
        dtype=torch.float64,
    )  # behind, just behind, inside near plane, just past it (straddling), close, normal
    scene["viewmat"] = torch.eye(4, dtype=torch.float64)
    scene["scales"] = torch.full((6, 3), 0.05, dtype=torch.float64)
    out, grads = _check_against_reference(scene, atol=1e-9)
    assert out.radii[:3].tolist() == [0, 0, 0]
    assert (out.radii[3:] > 0).all()
    assert torch.all(grads["means"][:3] == 0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_straddling_near_plane_float32_finite(dtype):
    scene = cast(single([0.0, 0.0, 0.0101], [0.05, 0.05, 0.05]), dtype)
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    assert out.alpha.min() > 0.5  # it covers the whole image


@pytest.mark.parametrize("scale", [1e-8, 1e3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_scales(scale, dtype):
    scene = random_scene(5, 20, 16, seed=3)
    scene["scales"][2] = scale
    scene = cast(scene, dtype)
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    if dtype == torch.float64:
        _check_against_reference(scene, atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_an_exact_zero_scale_is_finite(dtype):
    """A Gaussian of zero extent (all three scales exactly 0, a singular covariance) renders as
    the 2D blur alone, with finite values and gradients."""
    scene = random_scene(5, 20, 16, seed=4)
    scene["scales"][1] = 0.0
    scene = cast(scene, dtype)
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    if dtype == torch.float64:
        _check_against_reference(scene, atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_anisotropy_1e6(dtype):
    scene = random_scene(4, 30, 20, seed=8)
    scene["scales"][0] = torch.tensor([0.5, 5e-7, 5e-7])
    scene["scales"][1] = torch.tensor([1e-3, 1e3, 1e-3])
    scene = cast(scene, dtype)
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    if dtype == torch.float64:
        _check_against_reference(scene, atol=1e-8)
    else:
        ref_img = render_reference(scene)[0]
        assert (out.image.double() - ref_img).abs().mean() < 1e-4


def test_zero_quaternion_is_identity():
    scene = single([0.1, 0.0, 2.0], [0.2, 0.05, 0.1], quat=(0.0, 0.0, 0.0, 0.0))
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    assert torch.all(grads["quats"] == 0)
    ident = rasterize(**{**scene, "quats": torch.tensor([[3.0, 0, 0, 0]], dtype=torch.float64)})
    torch.testing.assert_close(out.image, ident.image, rtol=0, atol=1e-12)


def test_opacity_zero_and_one():
    zero = single([0.0, 0.0, 2.0], [0.3, 0.3, 0.3], opacity=0.0)
    out, grads = render_with_grads(zero)
    assert_finite(out, grads)
    assert torch.all(out.alpha == 0)
    torch.testing.assert_close(out.image, zero["background"].expand_as(out.image))

    one = single([0.0, 0.0, 2.0], [0.3, 0.3, 0.3], opacity=1.0)
    out, grads = _check_against_reference(one)
    assert out.alpha[12, 16, 0].item() == pytest.approx(0.999, abs=1e-12)  # clamped at the centre
    assert grads["opacities"].abs().item() > 0  # the unclamped rim still has a gradient


def test_gaussian_covering_whole_image():
    scene = single([0.0, 0.0, 2.0], [5.0, 5.0, 5.0], opacity=0.7)
    out, _ = _check_against_reference(scene)
    assert out.alpha.min() > 0.6 and out.alpha.max() <= 0.7


def test_hundreds_stacked_in_one_pixel_stop_early():
    # At pixel (7, 7) T = 0.5^k after k Gaussians: the 14th would take T to 6.1e-5 <= 1e-4, so
    # exactly 13 contribute.
    scene = stacked()
    _check_against_reference(scene, atol=1e-12)
    inputs = {k: (v.clone().requires_grad_(True) if k in PARAMS else v) for k, v in scene.items()}
    out = rasterize(**inputs)
    torch.testing.assert_close(out.alpha[7, 7, 0].item(), 1 - 0.5**13, rtol=0, atol=1e-12)
    weights = 0.5 ** torch.arange(1, 14, dtype=torch.float64)
    torch.testing.assert_close(out.image[7, 7], (weights[:, None] * scene["colors"][:13]).sum(0) + 0.5**13)
    out.image[7, 7].sum().backward()
    g = inputs["colors"].grad
    torch.testing.assert_close(g[:13], weights[:, None].expand(13, 3))
    assert torch.all(g[13:] == 0)  # past the stop: no gradient
    assert torch.isfinite(inputs["means"].grad).all() and torch.isfinite(inputs["opacities"].grad).all()


def test_gaussians_far_outside_the_image():
    scene = random_scene(3, 20, 16, seed=2)
    scene["means"] = torch.tensor([[50.0, 0, 3], [0, -80.0, 3], [1e6, 1e6, 3]], dtype=torch.float64)
    out, grads = render_with_grads(scene)
    assert_finite(out, grads)
    assert out.radii.tolist() == [0, 0, 0]
    torch.testing.assert_close(out.image, scene["background"].expand_as(out.image))
    assert torch.all(grads["means"] == 0)


def test_bad_inputs_raise_clear_errors():
    scene = random_scene(4, 8, 8)
    with pytest.raises(ValueError, match="quats"):
        rasterize(**{**scene, "quats": scene["quats"][:3]})
    with pytest.raises(ValueError, match="background"):
        rasterize(**{**scene, "background": torch.zeros(4, dtype=torch.float64)})
    with pytest.raises(ValueError, match="image size"):
        rasterize(**{**scene, "width": 0})
    with pytest.raises(ValueError, match="dtype"):
        rasterize(**{**scene, "colors": scene["colors"].float()})
    with pytest.raises(ValueError, match="backend"):
        RasterConfig(backend="cuda")


def test_sh_colors_match_eval_sh():
    scene = random_scene(20, 24, 20, seed=6)
    coeffs = 0.3 * torch.randn(20, 16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = rasterize(**{**scene, "colors": coeffs}, sh_degree=3)
    rgb = eval_sh(3, coeffs, view_dirs(scene["means"], scene["viewmat"]))
    expect = rasterize(**{**scene, "colors": rgb})
    torch.testing.assert_close(out.image, expect.image, rtol=0, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (CI has none)")
def test_cuda_matches_cpu():
    scene = cast(random_scene(200, 64, 48, seed=12, spread=0.4), torch.float32)
    cpu_out, cpu_grads = render_with_grads(scene)
    cuda_scene = {k: (v.cuda() if torch.is_tensor(v) else v) for k, v in scene.items()}
    out, grads = render_with_grads(cuda_scene)
    torch.testing.assert_close(out.image.cpu(), cpu_out.image, rtol=1e-4, atol=1e-5)
    for k in PARAMS:
        scale = cpu_grads[k].abs().max()
        assert (grads[k].cpu() - cpu_grads[k]).abs().max() <= 1e-3 * scale, k
