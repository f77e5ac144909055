"""The rasterizer's compiled C++ kernels against its pure-torch kernels, and how one is chosen.

Both implement the same rules (see eva_engine/render/composite.py), so on every scene, degenerate
ones included, images and gradients must agree to rounding: to ~1e-10 in float64, and within
float32 rounding in float32. The torch kernels themselves are checked against the brute-force and
autograd references in test_render.py.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
import torch
from helpers.render import PARAMS, cast, random_scene, render_with_grads, single, stacked

from eva_engine import native as native_lib
from eva_engine.render import RasterConfig, bin_gaussians, eval_sh, native, project_gaussians, rasterize

HAVE_COMPILER = shutil.which("c++") is not None and shutil.which("ninja") is not None


@pytest.fixture(scope="module")
def compiled():
    """The compiled kernels; a machine with a compiler must be able to build them."""
    if native.RASTER.load() is None:
        if HAVE_COMPILER:
            pytest.fail(f"the C++ kernels did not build: {native.RASTER.unavailable_reason()}")
        pytest.skip("no C++ compiler and ninja on this machine: the torch kernels run")
    return native.RASTER.load()


def assert_same(scene, tol64=(1e-10, 1e-8), rel32=2e-5, config=None):
    """Render ``scene`` with both kernels; outputs and all gradients must agree."""
    outs = {}
    for kernel in ("cpp", "torch"):
        cfg = RasterConfig(kernel=kernel, tile_size=config.tile_size if config else 8)
        outs[kernel] = render_with_grads(scene, cfg)
    (out_c, grads_c), (out_t, grads_t) = outs["cpp"], outs["torch"]
    assert out_c.num_intersections == out_t.num_intersections
    pairs = [(getattr(out_c, k), getattr(out_t, k), k) for k in ("image", "alpha", "depth")]
    pairs += [(grads_c[k], grads_t[k], k) for k in PARAMS]
    pairs.append((out_c.means2d.grad, out_t.means2d.grad, "means2d.grad"))
    for got, want, name in pairs:
        assert torch.isfinite(got).all(), name
        if got.dtype == torch.float64:
            atol, rtol = tol64
            torch.testing.assert_close(got, want, atol=atol, rtol=rtol, msg=name)
        else:
            scale = want.abs().max().clamp_min(1e-6)
            assert (got - want).abs().max() <= rel32 * scale, name
    return out_c, grads_c


# ----------------------------------------------------------------------------- random scenes


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize(
    ("n", "width", "height", "seed"), [(1, 16, 16, 0), (60, 37, 23, 1), (200, 64, 48, 2), (150, 100, 17, 3)]
)
def test_compiled_matches_torch_kernels(compiled, n, width, height, seed, dtype):
    # Partial tiles on both axes (37 x 23, 100 x 17) exercise the image-edge handling.
    assert_same(cast(random_scene(n, width, height, seed, spread=0.4), dtype))


def test_dense_scene_with_early_stops(compiled):
    scene = random_scene(300, 48, 40, seed=7, spread=0.3, size=(0.05, 0.2))
    scene["opacities"] = 0.6 + 0.39 * torch.rand(300, generator=torch.Generator().manual_seed(0)).double()
    assert_same(scene)
    assert_same(cast(scene, torch.float32), rel32=1e-4)


@pytest.mark.parametrize("channels", [1, 5])
def test_any_number_of_channels_and_no_background(compiled, channels):
    scene = random_scene(40, 24, 20, seed=11, channels=channels)
    assert_same(scene)
    scene["background"] = None
    out_c = rasterize(**scene, config=RasterConfig(kernel="cpp"))
    out_t = rasterize(**scene, config=RasterConfig(kernel="torch"))
    torch.testing.assert_close(out_c.image, out_t.image, atol=1e-10, rtol=0)


def test_tile_size_16(compiled):
    assert_same(random_scene(50, 45, 33, seed=9), config=RasterConfig(tile_size=16))


def test_sh_colors(compiled):
    scene = random_scene(20, 24, 20, seed=6)
    coeffs = 0.3 * torch.randn(20, 16, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out_c = rasterize(**{**scene, "colors": coeffs}, sh_degree=3, config=RasterConfig(kernel="cpp"))
    out_t = rasterize(**{**scene, "colors": coeffs}, sh_degree=3, config=RasterConfig(kernel="torch"))
    torch.testing.assert_close(out_c.image, out_t.image, atol=1e-10, rtol=0)


# ----------------------------------------------------------------------------- degenerate inputs


@pytest.mark.parametrize("opacity", [0.0, 1.0, 1e-13, 0.004])
def test_extreme_opacities(compiled, opacity):
    # 0 and 1e-13: nothing drawn; 1: alpha clamped at 0.999 (no gradient there); 0.004: just
    # above the 1/255 cutoff, only at the centre.
    assert_same(single([0.0, 0.0, 2.0], [0.3, 0.3, 0.3], opacity=opacity))


def test_stacked_gaussians_stop_early(compiled):
    scene = stacked()
    out, _ = assert_same(scene, tol64=(1e-12, 1e-9))
    torch.testing.assert_close(out.alpha[7, 7, 0].item(), 1 - 0.5**13, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_shapes_and_positions(compiled, dtype):
    scene = random_scene(8, 30, 20, seed=8)
    scene["scales"][0] = torch.tensor([0.5, 5e-7, 5e-7])  # needle
    scene["scales"][1] = torch.tensor([1e-3, 1e3, 1e-3])  # covers the image
    scene["scales"][2] = 1e-8  # a point: the eps2d blur only
    scene["means"][3] = torch.tensor([0.0, 0.05, 0.011])  # just past the near plane
    scene["means"][4] = torch.tensor([0.0, 0.0, -1.0])  # behind the camera
    scene["means"][5] = torch.tensor([1e6, 1e6, 3.0])  # far outside the image
    scene["quats"][6] = 0.0  # zero quaternion = identity
    scene["viewmat"] = torch.eye(4, dtype=torch.float64)
    assert_same(cast(scene, dtype), rel32=1e-4)


def test_saturated_and_faint_mix(compiled):
    scene = random_scene(120, 40, 32, seed=6, spread=0.3, size=(0.3, 0.6))
    scene["opacities"][::3] = 1.0
    scene["opacities"][1::7] = 0.003  # below 1/255 everywhere: never drawn
    assert_same(scene)


# ----------------------------------------------------------------------------- projection


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_projection_matches_torch(compiled, dtype):
    scene = random_scene(40, 30, 20, seed=4)
    scene["scales"][0] = torch.tensor([0.5, 5e-7, 5e-7])  # needle
    scene["scales"][1] = 1e-8  # point
    scene["means"][2] = torch.tensor([0.0, 0.0, -5.0])  # behind the camera (in world = camera frame)
    scene["means"][3] = torch.tensor([40.0, 0.0, 3.0])  # off the image, and its Jacobian clamped
    scene["quats"][4] = 0.0  # zero quaternion
    scene = cast(scene, dtype)
    names = ("means", "quats", "scales")
    g = torch.Generator().manual_seed(3)
    results = {}
    for kernel in ("cpp", "torch"):
        inputs = {k: scene[k].clone().requires_grad_(True) for k in names}
        proj = project_gaussians(
            inputs["means"],
            inputs["quats"],
            inputs["scales"],
            scene["viewmat"],
            scene["K"],
            30,
            20,
            kernel=kernel,
        )
        g.manual_seed(3)
        loss = sum(
            (t * torch.randn(t.shape, generator=g, dtype=dtype)).sum()
            for t in (proj.means2d, proj.conics, proj.compensations)
        )
        (loss + (proj.depths * torch.randn(40, generator=g, dtype=dtype)).sum()).backward()
        results[kernel] = (proj, {k: inputs[k].grad for k in names})
    (pc, gc), (pt, gt) = results["cpp"], results["torch"]
    assert torch.equal(pc.radii, pt.radii) and (pc.radii == 0).any()
    tol = dict(atol=1e-10, rtol=1e-9) if dtype == torch.float64 else dict(atol=1e-4, rtol=1e-4)
    for name in ("means2d", "conics", "depths", "compensations"):
        torch.testing.assert_close(getattr(pc, name), getattr(pt, name), msg=name, **tol)
    for name in names:
        assert torch.isfinite(gc[name]).all(), name
        torch.testing.assert_close(gc[name], gt[name], msg=name, **tol)
    assert torch.all(gc["quats"][4] == 0)


def test_projection_with_camera_gradients_runs_in_torch(compiled):
    scene = random_scene(5, 16, 12, seed=1)
    viewmat = scene["viewmat"].clone().requires_grad_(True)
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], viewmat, scene["K"], 16, 12)
    proj.means2d.sum().backward()
    assert viewmat.grad is not None and viewmat.grad.abs().sum() > 0


# ----------------------------------------------------------------------------- binning


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_binning_keeps_every_visible_pair(compiled, dtype):
    scene = cast(random_scene(150, 61, 45, seed=13, size=(0.005, 0.3)), dtype)
    proj = project_gaussians(
        *(scene[k] for k in ("means", "quats", "scales", "viewmat", "K", "width", "height"))
    )
    args = (proj.means2d, proj.radii, proj.depths, 61, 45, 8, proj.conics, scene["opacities"])
    c = bin_gaussians(*args, kernel="cpp")
    t = bin_gaussians(*args, kernel="torch")
    assert torch.equal(c.tile_start, c.tile_count.cumsum(0) - c.tile_count)
    assert torch.equal(c.tile_ids, torch.sort(c.tile_ids).values)
    kept_c = list(zip(c.gauss_ids.tolist(), c.tile_ids.tolist(), strict=True))
    kept_t = list(zip(t.gauss_ids.tolist(), t.tile_ids.tolist(), strict=True))
    if dtype == torch.float64:
        assert kept_c == kept_t  # same pairs, same front-to-back order
    else:
        # The compiled test runs in float64, the torch one in float32 with a rounding slack:
        # the same pairs up to that slack, in the same order.
        assert set(kept_c) <= set(kept_t) and len(kept_t) - len(kept_c) <= 0.01 * len(kept_t)
        assert [p for p in kept_t if p in set(kept_c)] == kept_c


def test_compiled_binning_orders_front_to_back_with_ties_by_index(compiled):
    """float32 depths take a radix sort: its order must be the stable argsort's, ties (equal
    depths) by index, and a depth the radix cannot order (zero, negative, NaN) falls back to the
    comparison sort."""
    gen = torch.Generator().manual_seed(3)
    n = 3000
    means2d = torch.rand(n, 2, generator=gen) * torch.tensor([32.0, 24.0])
    conics = torch.tensor([0.05, 0.0, 0.05]).repeat(n, 1)
    opacities = torch.full((n,), 0.9)
    radii = torch.full((n, 2), 12, dtype=torch.int32)
    radii[::7] = 0  # culled ones are left out
    depths = torch.randint(1, 40, (n,), generator=gen).float() * 0.25  # many equal depths
    for case in ("positive", "zero", "negative", "nan"):
        d = depths.clone()
        if case != "positive":
            d[5] = {"zero": 0.0, "negative": -1.0, "nan": float("nan")}[case]
        bins = bin_gaussians(means2d, radii, d, 32, 24, 8, conics, opacities, kernel="cpp")
        visible = torch.nonzero((radii > 0).all(dim=1)).squeeze(1)
        if case == "nan":  # NaN orders as the comparison sort leaves it; every pair is still there
            assert set(bins.gauss_ids.tolist()) <= set(visible.tolist())
            continue
        order = visible[torch.sort(d[visible], stable=True).indices]  # ties: by index
        rank = torch.empty(n, dtype=torch.long)
        rank[order] = torch.arange(len(order))
        for t in range(bins.num_tiles):
            s, c = int(bins.tile_start[t]), int(bins.tile_count[t])
            ids = bins.gauss_ids[s : s + c]
            assert torch.equal(rank[ids], torch.sort(rank[ids]).values), (case, t)


# ----------------------------------------------------------------------------- choosing a kernel


def test_kernel_choice(compiled, monkeypatch):
    like = torch.zeros(1, dtype=torch.float32)
    monkeypatch.delenv(native.KERNEL_ENV, raising=False)
    assert native.RASTER.resolve("auto", like) == "cpp"
    assert native.RASTER.resolve("torch", like) == "torch"
    assert native.RASTER.resolve("auto", like.half()) == "torch"  # dtypes the C++ does not take
    with pytest.raises(native.KernelUnavailableError):
        native.RASTER.resolve("cpp", like.half())
    monkeypatch.setenv(native.KERNEL_ENV, "torch")
    assert native.RASTER.resolve("auto", like) == "torch"
    assert native.RASTER.resolve("cpp", like) == "cpp"  # an explicit argument wins
    monkeypatch.setenv(native.KERNEL_ENV, "fast")
    with pytest.raises(ValueError, match=native.KERNEL_ENV):
        native.RASTER.resolve("auto", like)
    with pytest.raises(ValueError, match="kernel"):
        RasterConfig(kernel="cuda")


@pytest.mark.parametrize(
    ("module", "library", "variable"),
    [
        ("eva_engine.render.native", "RASTER", "EVA_RASTER_KERNEL"),
        ("eva_engine.avatar.skinning", "SKINNING", "EVA_SKINNING_KERNEL"),
    ],
)
def test_env_var_forces_the_torch_kernels_in_a_fresh_process(module, library, variable):
    code = (
        f"import torch; from {module} import {library} as lib; "
        "print(lib.resolve('auto', torch.zeros(1)), lib.state)"
    )
    env = {**__import__("os").environ, variable: "torch"}  # only this library's variable
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["torch", "{}"]  # nothing loaded or built


def test_failed_build_is_remembered(tmp_path):
    source = tmp_path / "broken.cpp"
    source.write_text("#error deliberately broken\n")
    with pytest.raises(Exception, match="Error building"):
        native_lib.build_library(source, tmp_path / "ext")
    marker = tmp_path / "ext" / f"{native_lib.library_name(source, 'eva_native')}.failed"
    assert marker.is_file()
    with pytest.raises(RuntimeError, match="earlier build failed"):
        native_lib.build_library(source, tmp_path / "ext")  # at once, no second compile
    assert native_lib.build_library(source, tmp_path / "other", build=False) is None


# ----------------------------------------------------------------------------- SH colours


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_sh_colours_match_the_torch_kernel(compiled, degree, dtype):
    gen = torch.Generator().manual_seed(degree)
    n = 300
    coeffs = (2.0 * torch.randn(n, 16, 3, generator=gen, dtype=dtype)).requires_grad_(True)
    dirs = torch.randn(n, 3, generator=gen, dtype=dtype)
    dirs[0] = 0.0  # a zero direction
    dirs[1] *= 1e-12  # a tiny one (squares stay normal floats: the torch kernel squares them)
    dirs[2] *= 1e15  # a huge one
    dirs.requires_grad_(True)
    weights = torch.randn(n, 3, generator=gen, dtype=dtype)
    out = {}
    for kernel in ("cpp", "torch"):
        rgb = eval_sh(degree, coeffs, dirs, kernel=kernel)
        grads = torch.autograd.grad((rgb * weights).sum(), [coeffs, dirs], allow_unused=True)
        # Degree 0 does not depend on the direction: no gradient (torch) or zeros (compiled).
        out[kernel] = (
            rgb,
            *(torch.zeros_like(x) if g is None else g for g, x in zip(grads, [coeffs, dirs], strict=True)),
        )
    assert (out["torch"][0] == 0).any()  # some colours clamped at 0: their gradient is cut
    tol = {"atol": 1e-12, "rtol": 1e-10} if dtype == torch.float64 else {"atol": 1e-5, "rtol": 1e-5}
    for a, b in zip(out["cpp"], out["torch"], strict=True):
        assert torch.isfinite(a).all()
        torch.testing.assert_close(a, b, **tol)


def test_sh_colours_gradcheck(compiled):
    gen = torch.Generator().manual_seed(0)
    coeffs = torch.randn(5, 16, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    dirs = torch.randn(5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, d: eval_sh(3, c, d, kernel="cpp"), (coeffs, dirs))
