"""Pixel-level image metrics: PSNR (optionally over a mask) and SSIM (pytorch-msssim).

Images are ``[B, C, H, W]`` float tensors in [0, data_range]; every metric returns ``[B]``.
"""

from __future__ import annotations

import pytorch_msssim
import torch
from torch import Tensor

from .regions import as_bool_mask

SSIM_WIN_SIZE = 11
SSIM_SIGMA = 1.5


def _check_pair(img: Tensor, ref: Tensor) -> None:
    if img.ndim != 4:
        raise ValueError(f"expected images [B, C, H, W], got {tuple(img.shape)}")
    if img.shape != ref.shape:
        raise ValueError(f"image shapes differ: {tuple(img.shape)} vs {tuple(ref.shape)}")


def mse(img: Tensor, ref: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean squared error per image. img, ref: ``[B, C, H, W]``; mask: ``[B, 1, H, W]`` -> ``[B]``.

    With a mask, the mean runs over the masked pixels (all channels). An empty mask for any image
    raises ValueError: there is no region to measure.
    """
    _check_pair(img, ref)
    sq = (img - ref) ** 2
    if mask is None:
        return sq.mean(dim=(1, 2, 3))
    mask = as_bool_mask(mask, like=img)
    count = mask.sum(dim=(1, 2, 3))
    if bool((count == 0).any()):
        empty = torch.nonzero(count == 0).flatten().tolist()
        raise ValueError(f"mask is empty for batch items {empty}: no region to measure")
    weight = mask.to(sq.dtype)
    return (sq * weight).sum(dim=(1, 2, 3)) / (count.to(sq.dtype) * img.shape[1])


def psnr(img: Tensor, ref: Tensor, mask: Tensor | None = None, data_range: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB, ``10 log10(data_range^2 / MSE)``, per image.

    img, ref: ``[B, C, H, W]``; mask: optional ``[B, 1, H, W]`` (PSNR over the masked pixels)
    -> ``[B]``. Identical images give +inf.
    """
    return 10.0 * torch.log10(data_range**2 / mse(img, ref, mask))


def ssim(img: Tensor, ref: Tensor, data_range: float = 1.0) -> Tensor:
    """Structural similarity per image (Wang et al. 2004), via pytorch-msssim.

    Gaussian window 11, sigma 1.5, K = (0.01, 0.03), population statistics over the valid
    (unpadded) window positions, averaged over channels — the same value as
    ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=data_range, channel_axis=...)``.
    img, ref: ``[B, C, H, W]`` with H, W >= 11 -> ``[B]``. Differentiable (``1 - ssim`` is the
    usual loss). For a region, crop first (``crop_to_mask_bbox``).
    """
    _check_pair(img, ref)
    if min(img.shape[-2:]) < SSIM_WIN_SIZE:
        raise ValueError(f"SSIM needs H, W >= {SSIM_WIN_SIZE}, got {tuple(img.shape[-2:])}")
    # Channels-last memory: oneDNN's depthwise Gaussian filter runs ~2.5x faster on it than on
    # [B, C, H, W] planes (bench: a 441 x 284 crop, forward + backward 42 -> 16 ms).
    img, ref = (x.contiguous(memory_format=torch.channels_last) for x in (img, ref))
    return pytorch_msssim.ssim(
        img, ref, data_range=data_range, size_average=False, win_size=SSIM_WIN_SIZE, win_sigma=SSIM_SIGMA
    )
