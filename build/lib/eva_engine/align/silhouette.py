"""The person mask as a fitting target: a two-sided chamfer between the mask's outline and the
projected body.

Keypoints fix the joints, not the outline around them: on real video a hunched torso or a bowed
head can put every keypoint and face-mesh landmark within a pixel while the fitted shoulders and
cranium sit several pixels inside the person's outline, and an avatar trained and tested with
those poses misses that band in every such frame (``docs/alignment.md``, "The outline"). Two
terms, both Geman-McClure in person heights like the keypoints:

- *inside*: a projected body point outside the mask is pulled toward it by the mask's distance
  transform (bilinearly sampled, so it has a gradient);
- *cover*: each sampled point of the mask's outline is pulled toward the nearest projected body
  point, so a band of mask that no part of the body reaches pulls the nearest part out to it.

The body is a fixed random subset of the model's vertices (every part of the surface, the same
points in every frame); an outline point within half the sample's spacing of it costs nothing
(``silhouette_loss``). Hair and loose clothes make *cover* pull outward where the body itself
is not; the robust scale keeps that bounded, and the avatar, not the fit, models them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from eva_engine.align.robust import geman_mcclure, weighted_gm

BORDER_PX = 2
"""Outline points this close to the image edge are the frame's edge, not the person's."""


@dataclass
class SilhouetteTargets:
    """What the silhouette terms compare against, for F frames of H x W.

    outside_distance: [F, 1, H, W] pixels from each pixel to the nearest mask pixel (0 inside);
    outline: [F, P, 2] pixel positions of points spread along the mask's outline;
    outline_weight: [F, P] 1 for a real point, 0 for padding (a frame without an outline).
    """

    outside_distance: Tensor
    outline: Tensor
    outline_weight: Tensor

    @classmethod
    def from_masks(
        cls, masks: Tensor | np.ndarray, points: int = 256, threshold: float = 0.5
    ) -> SilhouetteTargets:
        """From person masks [F, H, W] in [0, 1]. A frame whose mask is empty or covers the whole
        image (no mask was found) contributes nothing."""
        m = np.asarray(masks.detach().cpu() if isinstance(masks, Tensor) else masks, dtype=np.float32)
        if m.ndim != 3:
            raise ValueError(f"masks must be [F, H, W], got {m.shape}")
        f, h, w = m.shape
        dist = np.zeros((f, 1, h, w), np.float32)
        outline = np.zeros((f, points, 2), np.float32)
        weight = np.zeros((f, points), np.float32)
        for i in range(f):
            inside = np.nan_to_num(m[i]) > threshold
            if inside.all() or not inside.any():
                continue
            dist[i, 0] = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 5)
            contours, _ = cv2.findContours(inside.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            xy = np.concatenate([c.reshape(-1, 2) for c in contours], 0).astype(np.float32)
            away = (
                (xy[:, 0] >= BORDER_PX)
                & (xy[:, 1] >= BORDER_PX)
                & (xy[:, 0] < w - BORDER_PX)
                & (xy[:, 1] < h - BORDER_PX)
            )
            xy = xy[away]
            if len(xy) == 0:
                continue
            pick = np.linspace(0, len(xy) - 1, min(points, len(xy))).round().astype(np.int64)
            outline[i, : len(pick)] = xy[pick]
            weight[i, : len(pick)] = 1.0
        return cls(torch.from_numpy(dist), torch.from_numpy(outline), torch.from_numpy(weight))

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.outside_distance.shape[2]), int(self.outside_distance.shape[3])

    def to(self, device: torch.device | str) -> SilhouetteTargets:
        fields = (self.outside_distance, self.outline, self.outline_weight)
        return SilhouetteTargets(*(t.to(device) for t in fields))


def silhouette_vertices(num_vertices: int, count: int = 2500, seed: int = 0) -> Tensor:
    """[min(count, V)] sorted vertex indices: a fixed random subset of the surface."""
    g = torch.Generator().manual_seed(seed)
    return torch.randperm(num_vertices, generator=g)[: min(count, num_vertices)].sort().values


def silhouette_loss(
    uv: Tensor, targets: SilhouetteTargets, scale: Tensor, sigma: float, tolerance: Tensor | float = 0.0
) -> Tensor:
    """The inside and cover terms (module docstring), summed.

    uv: [F, V, 2] projected body points (pixels); scale: [F] person size in pixels (residuals
    are in its units); sigma: the Geman-McClure scale in the same units; tolerance: [F] or a
    scalar, pixels of an outline point's distance to its nearest body point that cost nothing.
    The body points are a sample of the surface, so even on the true outline the nearest one
    lies about half their spacing away: without the tolerance, cover would pull the sample, and
    the body with it, out to the outline and fatten it.
    """
    h, w = targets.image_size
    on_image = (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    has_mask = targets.outline_weight.sum(1) > 0  # [F]
    grid = torch.stack([uv[..., 0] / (w - 1), uv[..., 1] / (h - 1)], -1) * 2.0 - 1.0
    outside = F.grid_sample(
        targets.outside_distance, grid[:, :, None], mode="bilinear", padding_mode="border", align_corners=True
    )[:, 0, :, 0]  # [F, V] pixels
    inside_w = (on_image & has_mask[:, None]).to(uv.dtype)
    # A sum over the body points per outline point, like cover: a mean over all of them would
    # let the few outside the mask vanish among the many inside it, and cover would win.
    inside = (inside_w * geman_mcclure(outside / scale[:, None], sigma)).sum()
    inside = inside / targets.outline_weight.sum().clamp_min(1.0)
    # The nearest projected point to each outline point; the residual's gradient reaches that
    # point (the choice itself is piecewise constant), without an [F, P, V] graph.
    with torch.no_grad():
        chunks = range(0, uv.shape[0], 16)
        line = targets.outline
        nearest = torch.cat([torch.cdist(line[i : i + 16], uv[i : i + 16]).argmin(-1) for i in chunks])
    reached = uv.gather(1, nearest[..., None].expand(-1, -1, 2))
    gap = (reached - targets.outline).square().sum(-1).clamp_min(1e-12).sqrt()  # [F, P]
    tol = torch.as_tensor(tolerance, dtype=uv.dtype, device=uv.device).reshape(-1, 1)
    beyond = (gap - tol).clamp_min(0.0)
    cover = weighted_gm((beyond / scale[:, None])[..., None], targets.outline_weight, sigma)
    return inside + cover
