"""Image metrics: LPIPS(alex, v0.1) against the reference, SSIM against scikit-image, PSNR, regions."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view
from PIL import Image
from skimage.metrics import structural_similarity

from eva_engine.metrics import (
    LPIPS,
    LPIPSWeightsError,
    crop_to_mask_bbox,
    load_lpips_weights,
    lpips_weights_path,
    mask_bbox,
    prepare_lpips,
    psnr,
    ssim,
)
from eva_engine.numpy_pickle import load_numpy_pickle

LPIPS_IMAGES = Path(__file__).resolve().parent / "data" / "lpips"  # vendored, BSD-2 (LICENSE there)

# LPIPS v0.1 of the reference repo's example images, (ex_ref, ex_p0) and (ex_ref, ex_p1), with the
# official weights, published to 3 decimals: AlexNet "Distances: (0.722, 0.138)" as printed by its
# test_network.py (richzhang/PerceptualSimilarity issue #120); VGG 0.569 and 0.422 (the official
# PyTorch model's values, quoted in the README of moono/lpips-tf2.x).
PUBLISHED = {"alex": (0.722, 0.138), "vgg": (0.569, 0.422)}


@pytest.fixture(scope="module")
def lpips_model() -> LPIPS:
    return LPIPS()


@pytest.fixture(scope="module")
def lpips_nets(lpips_model) -> dict[str, LPIPS]:
    return {"alex": lpips_model, "vgg": LPIPS("vgg")}


def _load_uint8(name: str) -> np.ndarray:
    return np.asarray(Image.open(LPIPS_IMAGES / name).convert("RGB"))


def _to_tensor(img: np.ndarray) -> torch.Tensor:
    """[H, W, 3] uint8 -> [1, 3, H, W] float32 in [0, 1]."""
    return torch.from_numpy(img.astype(np.float32) / 255.0).permute(2, 0, 1)[None].contiguous()


# ---------------------------------------------------------------- LPIPS: reference values


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_matches_published_reference_values(lpips_nets, net):
    model = lpips_nets[net]
    ref, p0, p1 = (_load_uint8(f"ex_{n}.png") for n in ("ref", "p0", "p1"))
    d0 = model(_to_tensor(ref), _to_tensor(p0)).item()
    d1 = model(_to_tensor(ref), _to_tensor(p1)).item()
    assert (round(d0, 3), round(d1, 3)) == PUBLISHED[net], (d0, d1)
    # The reference's own input convention: uint8 / 127.5 - 1 with normalize=False.
    signed = [torch.from_numpy(im.astype(np.float32) / 127.5 - 1).permute(2, 0, 1)[None] for im in (ref, p0)]
    assert model(*signed, normalize=False).item() == pytest.approx(d0, abs=1e-6)


# (stride, padding) per conv, pool-after conv indices, pool (kernel, stride), tapped convs, trunk key
_NUMPY_LAYOUT = {
    "alex": ([(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)], (0, 1), (3, 2), (0, 1, 2, 3, 4), "AlexNet_0"),
    "vgg": ([(1, 1)] * 13, (1, 3, 6, 9), (2, 2), (1, 3, 6, 9, 12), "VGG16_0"),
}


def _numpy_lpips(net: str, params: dict, x0: np.ndarray, x1: np.ndarray) -> tuple[np.ndarray, list]:
    """Independent float64 LPIPS in the checkpoint's own flax layout (NHWC images, HWIO kernels).

    x0, x1: [N, H, W, 3] in [-1, 1] -> ([N], per-tap [N] contributions). Shares no code with the
    torch port (no kernel transposition, no torch convolution); the layout is written out here.
    """
    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])
    layout, pool_after, (pk, ps), tapped, trunk = _NUMPY_LAYOUT[net]

    def conv(x, kernel, bias, stride, pad):
        x = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
        kh, kw = kernel.shape[:2]
        win = sliding_window_view(x, (kh, kw), axis=(1, 2))[:, ::stride, ::stride]  # [N,Ho,Wo,C,kh,kw]
        return np.einsum("nhwcij,ijco->nhwo", win, kernel.astype(np.float64), optimize=True) + bias

    def maxpool(x):
        return sliding_window_view(x, (pk, pk), axis=(1, 2))[:, ::ps, ::ps].max(axis=(-2, -1))

    def taps(x):
        x = (x - shift) / scale
        out = []
        for i, (stride, pad) in enumerate(layout):
            conv_p = params[trunk][f"Conv_{i}"]
            x = np.maximum(conv(x, conv_p["kernel"], conv_p["bias"], stride, pad), 0.0)
            if i in tapped:
                out.append(x)
            if i in pool_after:
                x = maxpool(x)
        return out

    per_tap = []
    for i, (f0, f1) in enumerate(zip(taps(x0), taps(x1), strict=True)):
        n0 = f0 / (np.sqrt((f0**2).sum(-1, keepdims=True)) + 1e-10)
        n1 = f1 / (np.sqrt((f1**2).sum(-1, keepdims=True)) + 1e-10)
        lin = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"][0, 0, :, 0].astype(np.float64)
        per_tap.append((((n0 - n1) ** 2) @ lin).mean(axis=(1, 2)))
    return sum(per_tap), per_tap


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_matches_independent_numpy_forward(lpips_nets, net):
    params = load_numpy_pickle(lpips_weights_path(net))
    rng = np.random.default_rng(0)
    ref, p0, p1 = (_load_uint8(f"ex_{n}.png") for n in ("ref", "p0", "p1"))
    pairs = [
        (np.stack([ref, ref]) / 127.5 - 1, np.stack([p0, p1]) / 127.5 - 1),
        # non-square, so a swapped H/W or kernel transpose cannot hide
        (rng.uniform(-1, 1, (2, 47, 70, 3)), rng.uniform(-1, 1, (2, 47, 70, 3))),
    ]
    model64 = LPIPS(net).double()
    for x0, x1 in pairs:
        expected, expected_taps = _numpy_lpips(net, params, x0, x1)
        t0, t1 = (torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))) for x in (x0, x1))
        got64 = model64(t0, t1, normalize=False).numpy()
        np.testing.assert_allclose(got64, expected, rtol=0, atol=1e-10)
        # per-tap contributions: rebuild them from the port's own feature taps
        f0, f1 = model64.features(t0), model64.features(t1)
        for i, (a, b) in enumerate(zip(f0, f1, strict=True)):
            na = a / (a.norm(dim=1, keepdim=True) + 1e-10)
            nb = b / (b.norm(dim=1, keepdim=True) + 1e-10)
            tap = model64.lins[i]((na - nb) ** 2).mean(dim=(1, 2, 3)).numpy()
            np.testing.assert_allclose(tap, expected_taps[i], rtol=0, atol=1e-10)
        got32 = lpips_nets[net](t0.float(), t1.float(), normalize=False).numpy()
        np.testing.assert_allclose(got32, expected, rtol=0, atol=2e-5)


# ---------------------------------------------------------------- LPIPS: behaviour


def test_lpips_identity_symmetry_and_batch(lpips_model):
    torch.manual_seed(0)
    a, b = torch.rand(3, 3, 40, 56), torch.rand(3, 3, 40, 56)
    with torch.no_grad():
        assert torch.equal(lpips_model(a, a), torch.zeros(3))
        d_ab, d_ba = lpips_model(a, b), lpips_model(b, a)
        singles = torch.cat([lpips_model(a[i : i + 1], b[i : i + 1]) for i in range(3)])
    assert d_ab.shape == (3,)
    assert (d_ab > 0).all()
    torch.testing.assert_close(d_ab, d_ba, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(d_ab, singles, rtol=1e-5, atol=1e-6)
    # float64 inputs are accepted (cast to the module's dtype)
    torch.testing.assert_close(lpips_model(a.double(), b.double()), d_ab)


def test_lpips_is_frozen_but_differentiable(lpips_model):
    assert all(not p.requires_grad for p in lpips_model.parameters())
    lpips_model.train()
    assert not lpips_model.training
    torch.manual_seed(1)
    target = torch.rand(2, 3, 64, 64)
    degenerate = torch.stack([torch.zeros(3, 64, 64), torch.ones(3, 64, 64)])  # flat black / white
    for img in (torch.rand(2, 3, 64, 64), degenerate, target.clone()):
        img.requires_grad_(True)
        lpips_model(img, target).sum().backward()
        assert torch.isfinite(img.grad).all()
    assert all(p.grad is None for p in lpips_model.parameters())
    # a few steps of gradient descent on LPIPS reduce it (it works as a loss)
    img = torch.rand(1, 3, 64, 64, requires_grad=True)
    opt = torch.optim.Adam([img], lr=0.02)
    start = lpips_model(img, target[:1]).item()
    for _ in range(10):
        opt.zero_grad()
        lpips_model(img, target[:1]).sum().backward()
        opt.step()
    assert lpips_model(img, target[:1]).item() < start


def test_lpips_against_a_fixed_reference_equals_the_batched_pass(lpips_model):
    """A loss against a fixed target runs the target without backward, or reuses its features:
    same value and gradient as both images in one batch."""
    torch.manual_seed(2)
    img, target = torch.rand(1, 3, 48, 40), torch.rand(1, 3, 48, 40)
    values, grads = [], []
    for mode in ("batched", "reference", "cached"):
        x = img.clone().requires_grad_(True)
        if mode == "batched":  # a target that requires grad forces the one-batch pass
            value = lpips_model(x, target.clone().requires_grad_(True))
        elif mode == "reference":
            value = lpips_model(x, target)
        else:
            value = lpips_model(x, target, img1_features=lpips_model.reference_features(target))
        value.sum().backward()
        values.append(value.detach())
        grads.append(x.grad)
    for v, g in zip(values[1:], grads[1:], strict=True):
        assert torch.allclose(v, values[0], atol=1e-6) and torch.allclose(g, grads[0], atol=1e-7)


def test_the_training_loss_computes_a_targets_lpips_features_once(monkeypatch):
    from types import SimpleNamespace

    from eva_engine.train import AvatarLoss, LossConfig

    loss = AvatarLoss(LossConfig())
    calls = []
    reference = loss.lpips.reference_features
    monkeypatch.setattr(loss.lpips, "reference_features", lambda x: calls.append(1) or reference(x))
    torch.manual_seed(3)
    mask = torch.zeros(64, 64)
    mask[8:56, 16:48] = 1.0
    target = torch.rand(64, 64, 3)
    image, depth = torch.rand(64, 64, 3), torch.ones(64, 64, 1)
    render = SimpleNamespace(image=image, alpha=mask[..., None].clone(), depth=depth)
    plain = loss(render, target, mask)["lpips"]
    first = loss(render, target, mask, key=7)["lpips"]
    again = loss(render, target, mask, key=7)["lpips"]
    assert len(calls) == 2  # without a key, then once for key 7
    assert torch.allclose(plain, first) and torch.allclose(first, again)
    tight = AvatarLoss(LossConfig(lpips_cache_mb=0.0), lpips=loss.lpips)
    tight(render, target, mask, key=7)
    tight(render, target, mask, key=7)
    assert len(calls) == 4  # over the budget: recomputed each time


@pytest.mark.parametrize(
    ("shape0", "shape1", "match"),
    [
        ((1, 3, 30, 64), (1, 3, 30, 64), "H, W >= 31"),
        ((1, 1, 64, 64), (1, 1, 64, 64), r"\[B, 3, H, W\]"),
        ((1, 3, 64, 64), (1, 3, 64, 65), "differ"),
    ],
)
def test_lpips_rejects_bad_input(lpips_model, shape0, shape1, match):
    with pytest.raises(ValueError, match=match):
        lpips_model(torch.rand(shape0), torch.rand(shape1))


@pytest.mark.parametrize(("net", "side"), [("alex", 31), ("vgg", 16)])
def test_lpips_smallest_input(lpips_nets, net, side):
    model = lpips_nets[net]
    assert model.min_side == side
    a, b = torch.rand(1, 3, side, side), torch.rand(1, 3, side, side)
    assert torch.isfinite(model(a, b)).all()
    with pytest.raises(ValueError, match=f"LPIPS\\({net}\\) needs H, W >= {side}"):
        model(a[..., 1:], b[..., 1:])


def test_lpips_vgg_identity_symmetry_and_gradients(lpips_nets):
    vgg = lpips_nets["vgg"]
    torch.manual_seed(3)
    a, b = torch.rand(2, 3, 40, 56), torch.rand(2, 3, 40, 56)
    with torch.no_grad():
        assert torch.equal(vgg(a, a), torch.zeros(2))
        torch.testing.assert_close(vgg(a, b), vgg(b, a), rtol=1e-6, atol=1e-7)
    flat = torch.stack([torch.zeros(3, 40, 56), torch.ones(3, 40, 56)]).requires_grad_(True)
    vgg(flat, b).sum().backward()
    assert torch.isfinite(flat.grad).all()
    with pytest.raises(ValueError, match="unknown LPIPS network"):
        LPIPS("squeeze")


# ---------------------------------------------------------------- LPIPS: weights


def test_prepare_lpips_finds_and_verifies_weights():
    paths = prepare_lpips()
    assert sorted(paths) == ["alex", "vgg"]
    assert paths["alex"].name == "alexnet.ckpt" and paths["vgg"].name == "vgg16.ckpt"
    vgg = load_lpips_weights(paths["vgg"], net="vgg")
    assert [w.shape[0] for w in vgg.conv_weights] == [64, 64, 128, 128, 256, 256, 256] + [512] * 6
    assert [tuple(w.shape) for w in vgg.lin_weights] == [(1, c, 1, 1) for c in (64, 128, 256, 512, 512)]
    weights = load_lpips_weights(paths["alex"])
    assert [tuple(w.shape) for w in weights.conv_weights] == [
        (64, 3, 11, 11),
        (192, 64, 5, 5),
        (384, 192, 3, 3),
        (256, 384, 3, 3),
        (256, 256, 3, 3),
    ]
    assert [tuple(w.shape) for w in weights.lin_weights] == [(1, c, 1, 1) for c in (64, 192, 384, 256, 256)]


def test_missing_weights_give_install_hint(monkeypatch):
    import eva_engine.metrics.lpips as lpips_module

    monkeypatch.setattr(lpips_module.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(LPIPSWeightsError, match="make install"):
        lpips_weights_path()
    with pytest.raises(LPIPSWeightsError, match="make install"):
        LPIPS()


def test_tampered_weights_are_refused(tmp_path):
    tampered = tmp_path / "alexnet.ckpt"
    shutil.copyfile(lpips_weights_path(), tampered)
    with open(tampered, "r+b") as f:
        f.seek(-16, os.SEEK_END)
        f.write(b"\x00" * 8)
    with pytest.raises(LPIPSWeightsError, match="SHA-256"):
        load_lpips_weights(tampered)
    # each network's file is pinned to its own digest
    with pytest.raises(LPIPSWeightsError, match="vgg file"):
        load_lpips_weights(lpips_weights_path("alex"), net="vgg")


# ---------------------------------------------------------------- SSIM / PSNR


def _smooth_pair(rng: np.random.Generator, b: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([np.sin(6 * xx + c) * np.cos(4 * yy - c) for c in range(3)]) * 0.4 + 0.5
    ref = np.clip(base[None] + rng.normal(0, 0.05, (b, 3, h, w)), 0, 1)
    img = np.clip(ref + rng.normal(0, 0.1, ref.shape), 0, 1)
    return img, ref


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_matches_skimage(dtype):
    rng = np.random.default_rng(0)
    noise = rng.uniform(0, 1, (2, 2, 3, 32, 32))
    pairs = [_smooth_pair(rng, 2, 48, 67), (noise[0], noise[1])]
    for img, ref in pairs:
        got = ssim(torch.from_numpy(img).to(dtype), torch.from_numpy(ref).to(dtype))
        expected = [
            structural_similarity(
                img[i],
                ref[i],
                gaussian_weights=True,
                sigma=1.5,
                use_sample_covariance=False,
                data_range=1.0,
                channel_axis=0,
            )
            for i in range(img.shape[0])
        ]
        assert got.shape == (img.shape[0],)
        np.testing.assert_allclose(got.double().numpy(), expected, atol=1e-4)
    same = torch.rand(1, 3, 20, 20)
    torch.testing.assert_close(ssim(same, same), torch.ones(1))


def test_ssim_rejects_too_small_images():
    with pytest.raises(ValueError, match="H, W >= 11"):
        ssim(torch.rand(1, 3, 10, 40), torch.rand(1, 3, 10, 40))


def test_psnr_known_values():
    ref = torch.rand(2, 3, 16, 16) * 0.8
    assert torch.allclose(psnr(ref + 0.1, ref), torch.tensor([20.0, 20.0]), atol=1e-4)
    assert torch.allclose(psnr(ref - 0.01, ref), torch.tensor([40.0, 40.0]), atol=1e-3)
    assert torch.allclose(psnr((ref + 0.1) * 255, ref * 255, data_range=255.0), torch.tensor([20.0, 20.0]))
    assert torch.isinf(psnr(ref, ref)).all()


def test_masked_psnr():
    ref = torch.full((2, 3, 10, 12), 0.5)
    mask = torch.zeros(2, 1, 10, 12, dtype=torch.bool)
    mask[0, :, 2:5, 3:9] = True
    mask[1, :, 7:, :] = True
    img = ref + 0.3  # error 0.3 outside the region ...
    img = torch.where(mask, ref + 0.1, img)  # ... and 0.1 inside it
    torch.testing.assert_close(psnr(img, ref, mask=mask), torch.tensor([20.0, 20.0]))
    torch.testing.assert_close(psnr(img, ref, mask=mask.float()), torch.tensor([20.0, 20.0]))
    full = 10 * math.log10(1 / ((0.1**2 * 18 + 0.3**2 * 102) / 120))
    assert psnr(img[:1], ref[:1]).item() == pytest.approx(full, abs=1e-4)
    with pytest.raises(ValueError, match="empty for batch items \\[1\\]"):
        psnr(img, ref, mask=torch.cat([mask[:1], torch.zeros_like(mask[1:])]))
    with pytest.raises(ValueError, match="mask must be"):
        psnr(img, ref, mask=mask[:, 0])


# ---------------------------------------------------------------- regions


def test_mask_bbox_and_pad_clamping():
    mask = torch.zeros(2, 1, 10, 20, dtype=torch.bool)
    mask[0, 0, 3:6, 4:9] = True
    mask[1, 0, 0, 19] = True  # a single pixel in the top-right corner
    assert mask_bbox(mask).tolist() == [[4, 3, 9, 6], [19, 0, 20, 1]]
    assert mask_bbox(mask, pad=2).tolist() == [[2, 1, 11, 8], [17, 0, 20, 3]]
    assert mask_bbox(mask, pad=100).tolist() == [[0, 0, 20, 10], [0, 0, 20, 10]]
    assert mask_bbox(mask.float()).tolist() == mask_bbox(mask).tolist()
    with pytest.raises(ValueError, match="empty for batch items \\[0\\]"):
        mask_bbox(torch.zeros(1, 1, 5, 5))
    with pytest.raises(ValueError, match="pad"):
        mask_bbox(mask, pad=-1)


def test_crop_to_mask_bbox():
    img = torch.arange(2 * 3 * 10 * 20, dtype=torch.float32).reshape(2, 3, 10, 20)
    ref = img + 1
    mask = torch.zeros(2, 1, 10, 20, dtype=torch.bool)
    mask[0, 0, 3:6, 4:9] = True
    mask[1, 0, 5:9, 6:12] = True
    a, b, m = crop_to_mask_bbox(img, ref, mask, mask=mask)  # union box: x 4..12, y 3..9
    assert a.shape == (2, 3, 6, 8) and m.shape == (2, 1, 6, 8) and m.dtype == torch.bool
    assert torch.equal(a, img[..., 3:9, 4:12]) and torch.equal(b, ref[..., 3:9, 4:12])
    assert int(m.sum()) == int(mask.sum())
    # a mask touching the border, pad clamped to the image
    edge = torch.zeros(1, 1, 10, 20, dtype=torch.bool)
    edge[0, 0, 8:, 17:] = True
    (crop,) = crop_to_mask_bbox(img[:1], mask=edge, pad=3)
    assert torch.equal(crop, img[:1, :, 5:10, 14:20])
    # min_size grows the box inside the image; capped at the image size
    (crop,) = crop_to_mask_bbox(img[:1], mask=edge, min_size=7)
    assert torch.equal(crop, img[:1, :, 3:10, 13:20])
    (crop,) = crop_to_mask_bbox(img[:1], mask=edge, min_size=50)
    assert crop.shape[-2:] == (10, 20)
    with pytest.raises(ValueError, match="empty"):
        crop_to_mask_bbox(img[:1], mask=torch.zeros_like(edge))
    with pytest.raises(ValueError, match="does not match"):
        crop_to_mask_bbox(img[:, :, :5], mask=mask)


def test_region_metrics_on_a_small_crop(lpips_model):
    torch.manual_seed(2)
    img, ref = torch.rand(1, 3, 96, 128), torch.rand(1, 3, 96, 128)
    hand = torch.zeros(1, 1, 96, 128, dtype=torch.bool)
    hand[0, 0, 90:, 120:] = True  # 6x8 pixels in a corner: too small for LPIPS(alex) as is
    a, b = crop_to_mask_bbox(img, ref, mask=hand, pad=2, min_size=31)
    assert a.shape == (1, 3, 31, 31)
    values = [lpips_model(a, b), ssim(a, b), psnr(a, b)]
    assert all(v.shape == (1,) and torch.isfinite(v).all() for v in values)
