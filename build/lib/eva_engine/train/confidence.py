"""EVA's confidence-aware photometric loss (paper §3.4, eq. 12-13), made well-posed.

A small feedback network E looks at the rendered image I_r and rendered depth D_r and predicts a
per-pixel confidence C = μ + exp(E(I_r, D_r)) (μ = 1); the photometric term is C ⊙ |I_r − I|.

As written, the loss has a trivial minimum: E → −∞ makes C = μ everywhere, i.e. plain L1 (the
official code, with conf = (1 + eˣ)/2 and its log term disabled, ends there too: a uniform 0.5).
Our choice, so that C means something and cannot collapse:

1. **E is fitted by a heteroscedastic (Laplace) likelihood** on the detached residual r:
   L_E = mean_R(C ⊙ |r| − a log C). Per pixel its minimum is C* = clamp(a / |r|, μ, C_max):
   confidence is high where the render agrees with the frame and falls to μ where it does not
   (misalignment, blur: the paper's motivation). The log term is what removes the trivial
   minimum; C_max (a soft bound on E) keeps C finite where |r| → 0.
2. **The avatar sees the confidence as a weight with mean 1**: the image term is
   mean(w ⊙ |r|) with w = C / mean_R(C) on the person region R (person mask or rendered alpha
   > 0.5) and w = 1 elsewhere, both detached. So the confidence redistributes the photometric
   weight within the person without changing its total (the other loss weights, tuned against
   L1, stay balanced), and the avatar cannot lower its loss by moving C.

E sees its inputs detached (the render should fit the frame, not steer its own weights); its
parameters are trained by the trainer's loss optimizer (``OptimConfig.loss_lr``). Registered as
``PHOTOMETRIC_LOSSES["confidence"]``; select it with ``LossConfig(photometric="confidence")``.

**The official code's form** (``OfficialConfidenceLoss``, ``PHOTOMETRIC_LOSSES
["confidence_official"]``; ``nets/refine_sr.py``, ``train.py`` of kolassa-tema/EVA_Official):
C = (1 + exp(E)) / 2 with E two 1×1 convolutions of [I_r, D_r] (4 -> 3, LeakyReLU 0.2, then
[input, hidden] 7 -> 1), Kaiming-normal weights ×0.1 and zero biases; the term is mean(C ⊙ |r|)
with the log term's weight 0, and the inputs are **not** detached: the render gets gradient
through C as well. Nothing stops E from lowering its loss by driving C to its floor 0.5 (a
plain L1 at half weight); the official runs train it anyway, and so does this form.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from eva_engine.layers import seeded_layer
from eva_engine.metrics import crop_box
from eva_engine.train.losses import PHOTOMETRIC_LOSSES, ConfidenceConfig, LossConfig, PhotometricLoss


class ConfidenceNet(nn.Module):
    """E: image [H, W, 3] and depth [H, W, 1] -> log(C − μ) [H, W], softly bounded above by
    log(C_max − μ) (E = u − softplus(u − x): linear below, so pixels driven towards μ do not drag
    shared weights into a saturated region). Two 3×3 convolutions and a 1×1 head,
    zero-initialised.

    The depth is alpha-blended camera z (``RenderOutput.depth``); it is divided by the image's
    mean expected depth of covered pixels, so the input does not depend on the camera distance.
    """

    def __init__(
        self, hidden: int = 16, max_log: float = math.log(9.0), generator: torch.Generator | None = None
    ) -> None:
        super().__init__()
        self.max_log = max_log
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        self.body = nn.Sequential(
            seeded_layer(nn.Conv2d, 4, hidden, 3, padding=1, generator=g),
            nn.ReLU(),
            seeded_layer(nn.Conv2d, hidden, hidden, 3, padding=1, generator=g),
            nn.ReLU(),
        )
        self.head = seeded_layer(nn.Conv2d, hidden, 1, 1, generator=g)
        self.reach = 2  # pixels an output sees on each side (two 3x3 convolutions)
        with torch.no_grad():
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)
        self.to(memory_format=torch.channels_last)

    def forward(self, image: Tensor, depth: Tensor, alpha: Tensor) -> Tensor:
        covered = alpha > 0.5
        z = depth / alpha.clamp_min(1e-6)
        ref = z[covered].mean() if bool(covered.any()) else depth.new_tensor(1.0)
        rel_depth = depth / ref.clamp_min(1e-6)  # premultiplied: ~alpha × relative depth
        # [H, W, 4] is already channels-last memory: oneDNN's fast layout for few channels.
        x = torch.cat([image, rel_depth], dim=-1).permute(2, 0, 1)[None]
        x = x.contiguous(memory_format=torch.channels_last)
        raw = self.head(self.body(x))[0, 0]
        return self.max_log - F.softplus(self.max_log - raw)


class ConfidenceLoss(PhotometricLoss):
    """Confidence-aware L1 (module docstring). Inputs as ``PhotometricLoss``: image, target
    [H, W, 3]; alpha, depth [H, W, 1]; mask [H, W] -> scalar (image term + E's fitting term)."""

    def __init__(
        self, config: ConfidenceConfig | None = None, generator: torch.Generator | None = None
    ) -> None:
        super().__init__()
        self.config = config or ConfidenceConfig()
        c = self.config
        self.net = ConfidenceNet(c.hidden, math.log(c.max_confidence - c.mu), generator)
        self.last_confidence: Tensor | None = None  # [H, W] of the latest call, for inspection

    @classmethod
    def from_loss_config(cls, config: LossConfig, generator: torch.Generator | None = None) -> ConfidenceLoss:
        return cls(config.confidence, generator)

    def confidence(self, image: Tensor, depth: Tensor, alpha: Tensor) -> Tensor:
        """[H, W] C = μ + exp(E(I_r, D_r)) on detached inputs; with ``downscale`` s > 1, E sees
        the inputs pooled s×s (the frame edge-padded to a multiple of s) and its output is
        upsampled bilinearly before the exp."""
        image, depth, alpha = image.detach(), depth.detach(), alpha.detach()
        s = self.config.downscale
        if s == 1:
            return self.config.mu + torch.exp(self.net(image, depth, alpha))
        h, w = image.shape[:2]
        x = torch.cat([image, depth, alpha], dim=-1).permute(2, 0, 1)[None]  # [1, 5, H, W]
        x = F.pad(x, (0, -w % s, 0, -h % s), mode="replicate")
        x = F.avg_pool2d(x, s)[0].permute(1, 2, 0)  # [H/s, W/s, 5]
        e = self.net(x[..., :3], x[..., 3:4], x[..., 4:5])
        e = F.interpolate(e[None, None], scale_factor=s, mode="bilinear", align_corners=False)
        return self.config.mu + torch.exp(e[0, 0, :h, :w])

    def region(self, alpha: Tensor, mask: Tensor) -> Tensor:
        """[H, W] bool: the person region R (mask or rendered coverage)."""
        t = self.config.region_threshold
        return (mask > t) | (alpha[..., 0].detach() > t)

    def fit_term(self, conf: Tensor, residual: Tensor, region: Tensor) -> Tensor:
        """E's objective mean_R(C |r| − a log C); residual is detached here. conf, residual,
        region: [H, W]."""
        nll = conf * residual.detach() - self.config.residual_scale * torch.log(conf)
        return nll[region].mean() if bool(region.any()) else nll.mean()

    @staticmethod
    def weights(conf: Tensor, region: Tensor) -> Tensor:
        """[H, W] detached weights: C / mean_R(C) on R, 1 elsewhere (mean 1 over R)."""
        conf = conf.detach()
        if not bool(region.any()):
            return torch.ones_like(conf)
        return torch.where(region, conf / conf[region].mean(), torch.ones_like(conf))

    def confidence_on_region(self, image: Tensor, depth: Tensor, alpha: Tensor, region: Tensor) -> Tensor:
        """[H, W] C, computed only on R's box grown by E's reach (μ outside it): C is used only
        on R, where this equals ``confidence`` on the whole frame (R holds every covered pixel,
        so E's depth reference is the same too) at a fraction of the cost. With ``downscale`` s
        the box is grown by the reach at E's scale plus the upsampling's pixel and snapped to
        the s-grid, so the pooled cells are the whole frame's."""
        if not bool(region.any()):
            return self.confidence(image, depth, alpha)
        h, w = region.shape
        s = self.config.downscale
        pad = (self.net.reach + 1) * s if s > 1 else self.net.reach
        x0, y0, x1, y1 = crop_box(region[None, None], pad=pad)
        x0, y0 = x0 - x0 % s, y0 - y0 % s
        x1, y1 = min(w, x1 + -x1 % s), min(h, y1 + -y1 % s)
        crop = self.confidence(image[y0:y1, x0:x1], depth[y0:y1, x0:x1], alpha[y0:y1, x0:x1])
        return F.pad(crop, (x0, w - x1, y0, h - y1), value=self.config.mu)

    def forward(self, image: Tensor, target: Tensor, alpha: Tensor, depth: Tensor, mask: Tensor) -> Tensor:
        residual = (image - target).abs().mean(dim=-1)  # [H, W]
        region = self.region(alpha, mask)
        conf = self.confidence_on_region(image, depth, alpha, region)
        self.last_confidence = conf.detach()
        return (self.weights(conf, region) * residual).mean() + self.fit_term(conf, residual, region)


PHOTOMETRIC_LOSSES["confidence"] = ConfidenceLoss


class OfficialConfidenceNet(nn.Module):
    """The official E and C (module docstring): image [H, W, 3], depth [H, W, 1] -> C [H, W],
    C = (1 + exp(E)) / 2 >= 0.5. E is capped at ``max_log`` before the exp (the official code has
    no cap: exp overflows to inf there long before a pixel could matter)."""

    def __init__(self, generator: torch.Generator | None = None, max_log: float = 30.0) -> None:
        super().__init__()
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        self.max_log = max_log
        self.conv1 = nn.utils.skip_init(nn.Conv2d, 4, 3, 1)
        self.conv2 = nn.utils.skip_init(nn.Conv2d, 7, 1, 1)
        with torch.no_grad():
            for conv in (self.conv1, self.conv2):  # refine_sr.default_init_weights(scale=0.1)
                nn.init.kaiming_normal_(conv.weight, generator=g)
                conv.weight.mul_(0.1)
                nn.init.zeros_(conv.bias)

    def forward(self, image: Tensor, depth: Tensor) -> Tensor:
        x = torch.cat([image, depth], dim=-1).permute(2, 0, 1)[None]  # [1, 4, H, W]
        hidden = F.leaky_relu(self.conv1(x), 0.2)
        e = self.conv2(torch.cat([x, hidden], dim=1))[0, 0]
        return (1.0 + torch.exp(e.clamp_max(self.max_log))) / 2.0


class OfficialConfidenceLoss(PhotometricLoss):
    """The official confidence-weighted L1 (module docstring): mean(C ⊙ |I_r − I|) over pixels
    and channels, C from the rendered image and depth with their gradients kept. Inputs as
    ``PhotometricLoss``."""

    def __init__(self, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.net = OfficialConfidenceNet(generator)
        self.last_confidence: Tensor | None = None

    def forward(self, image: Tensor, target: Tensor, alpha: Tensor, depth: Tensor, mask: Tensor) -> Tensor:
        conf = self.net(image, depth)
        self.last_confidence = conf.detach()
        return ((image - target).abs() * conf[..., None]).mean()


PHOTOMETRIC_LOSSES["confidence_official"] = OfficialConfidenceLoss
