"""Image regions given by masks: bounding boxes and crops (hand / face / body evaluation).

Masks are ``[B, 1, H, W]`` (bool, or numbers where > 0.5 counts as inside). Boxes are integer
pixel bounds ``(x0, y0, x1, y1)`` with x1, y1 exclusive, so ``img[..., y0:y1, x0:x1]`` is the crop.
"""

from __future__ import annotations

import torch
from torch import Tensor


def as_bool_mask(mask: Tensor, like: Tensor | None = None) -> Tensor:
    """Validate a region mask ``[B, 1, H, W]`` (matching ``like [B, C, H, W]`` if given) -> bool."""
    if mask.ndim != 4 or mask.shape[1] != 1:
        raise ValueError(f"mask must be [B, 1, H, W], got {tuple(mask.shape)}")
    if like is not None and (mask.shape[0] != like.shape[0] or mask.shape[-2:] != like.shape[-2:]):
        raise ValueError(f"mask {tuple(mask.shape)} does not match images {tuple(like.shape)}")
    return mask if mask.dtype == torch.bool else mask > 0.5


def mask_bbox(mask: Tensor, pad: int = 0) -> Tensor:
    """Per-image bounding box of a mask, grown by ``pad`` pixels and clamped to the image.

    mask: ``[B, 1, H, W]`` -> ``[B, 4]`` int64 ``(x0, y0, x1, y1)``, x1/y1 exclusive.
    Raises ValueError if any image's mask is empty (there is no region to box).
    """
    if pad < 0:
        raise ValueError(f"pad must be >= 0, got {pad}")
    m = as_bool_mask(mask)[:, 0]
    _, h, w = m.shape
    rows, cols = m.any(dim=2), m.any(dim=1)  # [B, H], [B, W]
    empty = ~rows.any(dim=1)
    if bool(empty.any()):
        raise ValueError(
            f"mask is empty for batch items {torch.nonzero(empty).flatten().tolist()}: no region to crop"
        )

    def bounds(hit: Tensor, size: int) -> tuple[Tensor, Tensor]:
        idx = torch.arange(size, device=hit.device)
        first = torch.where(hit, idx, size).amin(dim=1)
        last = torch.where(hit, idx, -1).amax(dim=1)
        return (first - pad).clamp(min=0), (last + 1 + pad).clamp(max=size)

    y0, y1 = bounds(rows, h)
    x0, x1 = bounds(cols, w)
    return torch.stack([x0, y0, x1, y1], dim=1).to(torch.int64)


def _grow(lo: int, hi: int, size: int, min_size: int) -> tuple[int, int]:
    """Grow [lo, hi) symmetrically to at least min_size, shifted to stay inside [0, size)."""
    need = min(min_size, size) - (hi - lo)
    if need <= 0:
        return lo, hi
    lo -= need // 2
    hi += need - need // 2
    if lo < 0:
        hi, lo = hi - lo, 0
    if hi > size:
        lo, hi = lo - (hi - size), size
    return lo, hi


def crop_box(mask: Tensor, pad: int = 0, min_size: int = 0) -> tuple[int, int, int, int]:
    """The crop box ``(x0, y0, x1, y1)`` of a region: the union over the batch of the per-image
    mask boxes, grown by ``pad`` pixels on every side (clamped to the image), then each side to
    at least ``min_size`` pixels (or the image size), kept inside the image. mask: ``[B, 1, H, W]``.
    Raises ValueError for an empty mask."""
    h, w = mask.shape[-2:]
    boxes = mask_bbox(mask, pad)
    x0, y0 = (int(v) for v in boxes[:, :2].amin(dim=0))
    x1, y1 = (int(v) for v in boxes[:, 2:].amax(dim=0))
    x0, x1 = _grow(x0, x1, w, min_size)
    y0, y1 = _grow(y0, y1, h, min_size)
    return x0, y0, x1, y1


def crop_to_mask_bbox(*images: Tensor, mask: Tensor, pad: int = 0, min_size: int = 0) -> tuple[Tensor, ...]:
    """Crop images to the :func:`crop_box` of ``mask`` (e.g. a hand region) for region metrics.

    images: any number of ``[B, C, H, W]`` tensors (any dtype; pass the mask too to crop it);
    mask: ``[B, 1, H, W]``. The box is the union over the batch of the per-image boxes, so the
    crops stay batched — crop one image at a time for per-image boxes. ``pad`` and ``min_size``
    as in :func:`crop_box` (e.g. ``min_size=31`` for LPIPS(alex) on small hand crops). Returns
    the crops ``[B, C, y1 - y0, x1 - x0]`` in order. Raises ValueError for an empty mask.
    """
    if not images:
        raise ValueError("crop_to_mask_bbox needs at least one image")
    h, w = mask.shape[-2:]
    for img in images:
        if img.ndim != 4 or img.shape[0] != mask.shape[0] or img.shape[-2:] != (h, w):
            raise ValueError(f"image {tuple(img.shape)} does not match mask {tuple(mask.shape)}")
    x0, y0, x1, y1 = crop_box(mask, pad, min_size)
    return tuple(img[..., y0:y1, x0:x1] for img in images)
