"""Training objective (EVA §3.4): L = L_photo + lambda_m L_mask + lambda_s L_SSIM + lambda_l L_LPIPS.

- L_photo: the per-pixel photometric term, chosen by name from ``PHOTOMETRIC_LOSSES``; this
  module ships ``"l1"`` (mean |I_r - I|, the 3DGS baseline); EVA's confidence-aware loss registers
  itself there as another entry (a module that may have parameters: the trainer optimises them).
- L_mask: mean squared error between the rendered alpha and the person mask (GauHuman's choice).
- L_SSIM = 1 - SSIM and L_LPIPS (AlexNet), both on the crop to the person's bounding box (grown
  to at least ``min_crop`` pixels per side), as the official code does: the background would
  otherwise dominate both.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import Tensor, nn

from eva_engine.metrics import LPIPS, crop_to_mask_bbox, ssim
from eva_engine.render import RenderOutput


@dataclass(frozen=True)
class LossConfig:
    """Loss weights (EVA: lambda_m = 0.1, lambda_s = 0.01, lambda_l = 0.04) and choices."""

    photometric: str = "l1"
    lambda_mask: float = 0.1
    lambda_ssim: float = 0.01
    lambda_lpips: float = 0.04
    crop_pad: int = 4
    min_crop: int = 32


class PhotometricLoss(nn.Module):
    """Per-pixel term: image, target [H, W, 3]; alpha, depth [H, W, 1]; mask [H, W] -> scalar."""

    def forward(self, image: Tensor, target: Tensor, alpha: Tensor, depth: Tensor, mask: Tensor) -> Tensor:
        raise NotImplementedError


class L1Loss(PhotometricLoss):
    """mean |I_r - I| over the whole image (3DGS)."""

    def forward(self, image: Tensor, target: Tensor, alpha: Tensor, depth: Tensor, mask: Tensor) -> Tensor:
        return (image - target).abs().mean()


PHOTOMETRIC_LOSSES: dict[str, Callable[[], PhotometricLoss]] = {"l1": L1Loss}


class AvatarLoss(nn.Module):
    """The full objective (module docstring). ``lpips`` is built lazily when its weight is > 0."""

    def __init__(self, config: LossConfig, lpips: LPIPS | None = None) -> None:
        super().__init__()
        if config.photometric not in PHOTOMETRIC_LOSSES:
            raise ValueError(f"unknown photometric loss {config.photometric!r}; "
                             f"choose one of {sorted(PHOTOMETRIC_LOSSES)}")  # fmt: skip
        self.config = config
        self.photometric = PHOTOMETRIC_LOSSES[config.photometric]()
        self.lpips = lpips if lpips is not None or config.lambda_lpips == 0 else LPIPS()

    def forward(self, render: RenderOutput, target: Tensor, mask: Tensor) -> dict[str, Tensor]:
        """render: the rasterizer output; target: [H, W, 3] composited on the render background;
        mask: [H, W] person coverage in [0, 1]. Returns the terms and ``"total"``."""
        cfg = self.config
        image = render.image
        terms = {"photometric": self.photometric(image, target, render.alpha, render.depth, mask)}
        total = terms["photometric"]
        if cfg.lambda_mask:
            terms["mask"] = ((render.alpha[..., 0] - mask) ** 2).mean()
            total = total + cfg.lambda_mask * terms["mask"]
        if cfg.lambda_ssim or cfg.lambda_lpips:
            img = image.clamp(0.0, 1.0).permute(2, 0, 1)[None]
            tgt = target.permute(2, 0, 1)[None]
            m = mask[None, None]
            if bool((m > 0.5).any()):
                img, tgt = crop_to_mask_bbox(img, tgt, mask=m, pad=cfg.crop_pad, min_size=cfg.min_crop)
            if cfg.lambda_ssim:
                terms["ssim"] = 1.0 - ssim(img, tgt)[0]
                total = total + cfg.lambda_ssim * terms["ssim"]
            if cfg.lambda_lpips:
                terms["lpips"] = self.lpips(img, tgt)[0]
                total = total + cfg.lambda_lpips * terms["lpips"]
        terms["total"] = total
        return terms


def composite_target(image: Tensor, mask: Tensor, background: Tensor) -> Tensor:
    """The training target: the person over the render background.
    image: [H, W, 3]; mask: [H, W] in [0, 1]; background: [3] -> [H, W, 3]."""
    m = mask[..., None]
    return image * m + background.to(image) * (1.0 - m)
