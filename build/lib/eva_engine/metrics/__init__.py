"""Image-quality metrics: PSNR, SSIM, LPIPS(alex, v0.1), and region helpers.

Images are ``[B, C, H, W]`` float tensors in [0, 1]; metrics return ``[B]``. Region metrics
(hands, face) use a mask: ``psnr(..., mask=...)`` over masked pixels, or any metric on the
mask's bounding-box crop (``crop_to_mask_bbox``). ``LPIPS`` is an ``nn.Module`` the caller
builds once and holds; ``prepare_lpips()`` checks its offline weights at install time.
"""

from .lpips import (
    LPIPS,
    LPIPSWeights,
    LPIPSWeightsError,
    load_lpips_weights,
    lpips_weights_path,
    prepare_lpips,
)
from .pixel import mse, psnr, ssim
from .regions import crop_box, crop_to_mask_bbox, mask_bbox

__all__ = [
    "LPIPS",
    "LPIPSWeights",
    "LPIPSWeightsError",
    "crop_box",
    "crop_to_mask_bbox",
    "load_lpips_weights",
    "lpips_weights_path",
    "mask_bbox",
    "mse",
    "prepare_lpips",
    "psnr",
    "ssim",
]
