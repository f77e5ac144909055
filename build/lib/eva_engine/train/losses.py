"""Training objective (EVA §3.4): L = λ_p L_photo + λ_m L_mask + λ_s L_SSIM + λ_l L_LPIPS.

- L_photo: the per-pixel photometric term, chosen by name from ``PHOTOMETRIC_LOSSES``; this
  module ships ``"l1"`` (mean |I_r - I|, the 3DGS baseline); EVA's confidence-aware loss registers
  itself there as another entry (a module that may have parameters: the trainer optimises them).
- L_mask: mean squared error between the rendered alpha and the person mask (GauHuman's choice).
- L_SSIM = 1 - SSIM and L_LPIPS (AlexNet; ``lpips_net="vgg"`` is the official code's), both on
  the crop to the person's box (its mask's bounding box grown by ``crop_pad``, then to at least
  ``min_crop`` pixels per side), as the official code does: the background would otherwise
  dominate both.
- Pixel normalisation (``pixel_norm``): the official code averages L_photo and L_mask over the
  person's box, not the frame, and the densification thresholds (3DGS's 2e-4, EVA's per-part e)
  were tuned with gradients of that size. With ``"person_box"`` (the default) the two pixel terms
  are summed over the whole frame (so a floater outside the box is still penalised) and divided
  by the box's area: every pixel weighs what it weighs in the official code. ``"frame"`` divides
  by the frame's area instead, which scales the screen-space gradients, and so the densification,
  down by box area / frame area (about 1/3 for a full-body 512 px frame).

EVA: λ_p = 1, λ_m = 0.1, λ_s = 0.01, λ_l = 0.04. 3DGS: λ_p = 0.8, λ_s = 0.2 (D-SSIM), no LPIPS.
Our default keeps EVA's weights but 3DGS's λ_s = 0.2: measured better on the held-out LPIPS-VGG
in every region, synthetic and real (``bench/results/ssim_weight/summary.md``,
``real_videos_ssim_vs_bs.md``); ``lambda_ssim=0.01`` is the paper's setting.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from eva_engine.metrics import LPIPS, crop_box, ssim
from eva_engine.render import RenderOutput

PIXEL_NORMS = ("person_box", "frame")
LPIPS_NETS = ("alex", "vgg")


@dataclass(frozen=True)
class ConfidenceConfig:
    """The confidence-aware term's settings (``train/confidence.py``). mu: the floor μ of C;
    residual_scale: a, pixels with |r| < a/μ get C > μ; max_confidence: C_max; hidden: E's
    channels; region_threshold: mask/alpha level of R; downscale: E runs on its inputs
    average-pooled by this factor and its output is upsampled bilinearly (2: a quarter of the
    pixels, the same trained layers; the residual and the weights stay at full resolution)."""

    mu: float = 1.0
    residual_scale: float = 0.1
    max_confidence: float = 10.0
    hidden: int = 16
    region_threshold: float = 0.5
    downscale: int = 1

    def __post_init__(self) -> None:
        if not 0.0 < self.mu < self.max_confidence:
            raise ValueError(f"need 0 < mu < max_confidence, got {self.mu}, {self.max_confidence}")
        if self.hidden < 1 or self.downscale < 1:
            raise ValueError(f"hidden and downscale must be >= 1, got {self.hidden}, {self.downscale}")


@dataclass(frozen=True)
class LossConfig:
    """Loss weights (EVA's λ_p = 1, λ_m = 0.1, λ_l = 0.04; 3DGS's λ_s = 0.2, the paper's is 0.01)
    and choices (module docstring)."""

    photometric: str = "l1"
    lambda_photometric: float = 1.0
    lambda_mask: float = 0.1
    lambda_ssim: float = 0.2
    lambda_lpips: float = 0.04
    pixel_norm: str = "person_box"
    crop_pad: int = 4
    min_crop: int = 32
    lpips_cache_mb: float = 512.0
    """Memory for the targets' LPIPS features, kept per training frame (a target never changes, so
    its pass through the network is done once); frames past the budget are recomputed."""
    lpips_every: int = 1
    """The LPIPS term on every k-th step only, weighted k λ_l there (the same expected gradient):
    its network's forward and backward are the costliest part of the loss on CPU."""
    lpips_every_from: int = 0
    """The step from which ``lpips_every`` applies; before it the LPIPS term runs on every step
    (e.g. thinned only after densification stops)."""
    lpips_net: str = "alex"
    """The LPIPS term's network. "alex" keeps LPIPS-VGG, the paper's metric, one no method trains
    on; "vgg" is the official code's loss (``loss_fn_vgg``): a row trained on it is trained on
    the metric it is scored with, and the tables mark it so."""
    confidence: ConfidenceConfig = field(default_factory=ConfidenceConfig)
    """``photometric="confidence"`` only: its network and constants."""

    def __post_init__(self) -> None:
        if self.pixel_norm not in PIXEL_NORMS:
            raise ValueError(f"pixel_norm must be one of {PIXEL_NORMS}, got {self.pixel_norm!r}")
        if self.lpips_every < 1:
            raise ValueError(f"lpips_every must be >= 1, got {self.lpips_every}")
        if self.lpips_every_from < 0:
            raise ValueError(f"lpips_every_from must be >= 0, got {self.lpips_every_from}")
        if self.lpips_net not in LPIPS_NETS:
            raise ValueError(f"lpips_net must be one of {LPIPS_NETS}, got {self.lpips_net!r}")


class PhotometricLoss(nn.Module):
    """Per-pixel term: image, target [H, W, 3]; alpha, depth [H, W, 1]; mask [H, W] -> scalar.
    Built as ``cls(generator=...)``: what draws the initial values of its learnable parts (if it
    has any; None: a generator seeded 0)."""

    def __init__(self, generator: torch.Generator | None = None) -> None:
        super().__init__()

    @classmethod
    def from_loss_config(
        cls, config: LossConfig, generator: torch.Generator | None = None
    ) -> PhotometricLoss:
        """The term as ``config`` asks for it (a term with settings of its own reads them here)."""
        return cls(generator=generator)

    def forward(self, image: Tensor, target: Tensor, alpha: Tensor, depth: Tensor, mask: Tensor) -> Tensor:
        raise NotImplementedError


class L1Loss(PhotometricLoss):
    """mean |I_r - I| over the whole image (3DGS)."""

    def forward(self, image: Tensor, target: Tensor, alpha: Tensor, depth: Tensor, mask: Tensor) -> Tensor:
        return (image - target).abs().mean()


PHOTOMETRIC_LOSSES: dict[str, type[PhotometricLoss]] = {"l1": L1Loss}


class AvatarLoss(nn.Module):
    """The full objective (module docstring). ``lpips`` is built lazily when its weight is > 0;
    ``generator`` draws the initial values of the photometric term's learnable parts."""

    def __init__(
        self, config: LossConfig, lpips: LPIPS | None = None, generator: torch.Generator | None = None
    ) -> None:
        super().__init__()
        if config.photometric not in PHOTOMETRIC_LOSSES:
            raise ValueError(
                f"unknown photometric loss {config.photometric!r}; choose one of {sorted(PHOTOMETRIC_LOSSES)}"
            )
        self.config = config
        self.photometric = PHOTOMETRIC_LOSSES[config.photometric].from_loss_config(config, generator)
        if lpips is not None and getattr(lpips, "net", config.lpips_net) != config.lpips_net:
            raise ValueError(f"the loss asks for LPIPS-{config.lpips_net}, got an LPIPS-{lpips.net} network")
        self.lpips = lpips if lpips is not None or config.lambda_lpips == 0 else LPIPS(config.lpips_net)
        self._target_features: dict[Hashable, tuple[tuple[int, int, int, int], list[Tensor]]] = {}
        self._cached_bytes = 0

    def target_features(self, key: Hashable | None, box: tuple[int, ...], target: Tensor) -> list[Tensor]:
        """LPIPS features of the target crop [1, 3, h, w], cached under ``key`` (a frame id) within
        ``lpips_cache_mb``."""
        hit = self._target_features.get(key) if key is not None else None
        if hit is not None and hit[0] == box:
            return hit[1]
        features = self.lpips.reference_features(target)
        size = sum(f.numel() * f.element_size() for f in features)
        if key is not None and self._cached_bytes + size <= self.config.lpips_cache_mb * 2**20:
            self._target_features[key] = (box, features)
            self._cached_bytes += size
        return features

    def person_box(self, mask: Tensor) -> tuple[int, int, int, int]:
        """``(x0, y0, x1, y1)``: the crop of the SSIM / LPIPS terms and the area the pixel terms
        are normalised by (the whole frame when the mask is empty). mask: [H, W]."""
        h, w = mask.shape
        m = mask[None, None] > 0.5
        if not bool(m.any()):
            return 0, 0, w, h
        return crop_box(m, pad=self.config.crop_pad, min_size=self.config.min_crop)

    def forward(
        self,
        render: RenderOutput,
        target: Tensor,
        mask: Tensor,
        key: Hashable | None = None,
        step: int | None = None,
    ) -> dict[str, Tensor]:
        """render: the rasterizer output; target: [H, W, 3] composited on the render background;
        mask: [H, W] person coverage in [0, 1]; key: the target's identity (e.g. its frame
        index) when the same target comes back, so its LPIPS features are reused; step: the
        training step (with ``lpips_every`` > 1 the LPIPS term runs on multiples of it from
        ``lpips_every_from`` on; None: always, weighted λ_l). Returns the terms and ``"total"``."""
        cfg = self.config
        image = render.image
        h, w = mask.shape
        x0, y0, x1, y1 = self.person_box(mask)
        # The pixel terms are frame means; rescaled to "per pixel of the person's box".
        scale = h * w / ((x1 - x0) * (y1 - y0)) if cfg.pixel_norm == "person_box" else 1.0
        photo = self.photometric(image, target, render.alpha, render.depth, mask)
        terms = {"photometric": scale * photo}
        total = cfg.lambda_photometric * terms["photometric"]
        if cfg.lambda_mask:
            terms["mask"] = scale * ((render.alpha[..., 0] - mask) ** 2).mean()
            total = total + cfg.lambda_mask * terms["mask"]
        every = cfg.lpips_every if step is not None and step >= cfg.lpips_every_from else 1
        lpips_now = cfg.lambda_lpips > 0 and (step is None or step % every == 0)
        if cfg.lambda_ssim or lpips_now:
            img = image.clamp(0.0, 1.0).permute(2, 0, 1)[None, :, y0:y1, x0:x1]
            tgt = target.permute(2, 0, 1)[None, :, y0:y1, x0:x1]
            if cfg.lambda_ssim:
                terms["ssim"] = 1.0 - ssim(img, tgt)[0]
                total = total + cfg.lambda_ssim * terms["ssim"]
            if lpips_now:
                features = self.target_features(key, (x0, y0, x1, y1), tgt)
                terms["lpips"] = self.lpips(img, tgt, img1_features=features)[0]
                total = total + every * cfg.lambda_lpips * terms["lpips"]
        terms["total"] = total
        return terms


def composite_target(image: Tensor, mask: Tensor, background: Tensor) -> Tensor:
    """The training target: the person over the render background.
    image: [H, W, 3]; mask: [H, W] in [0, 1]; background: [3] -> [H, W, 3]."""
    m = mask[..., None]
    return image * m + background.to(image) * (1.0 - m)
