"""Binning of projected Gaussians into square screen tiles (no gradients flow through here)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.render.native import RASTER, Kernel


@dataclass
class TileBins:
    """Gaussian-tile intersections sorted by (tile, camera depth), front to back within a tile.

    Tiles are numbered row-major: tile = ty * tiles_x + tx; tile (tx, ty) covers pixels
    [tx * tile_size, (tx + 1) * tile_size) x [ty * tile_size, (ty + 1) * tile_size).

    gauss_ids:  [M] int64 Gaussian index of each intersection.
    tile_ids:   [M] int64 tile of each intersection (non-decreasing).
    tile_start: [T] int64 first intersection of each tile (T = tiles_x * tiles_y).
    tile_count: [T] int64 intersections per tile.
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    gauss_ids: Tensor
    tile_ids: Tensor
    tile_start: Tensor
    tile_count: Tensor

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def num_intersections(self) -> int:
        return int(self.gauss_ids.shape[0])

    def tile_origins(self, tile_ids: Tensor, dtype: torch.dtype) -> Tensor:
        """[M] tile ids -> [M, 2] pixel coordinates (x, y) of the tiles' top-left corners."""
        tx = tile_ids % self.tiles_x
        ty = tile_ids // self.tiles_x
        return torch.stack([tx, ty], dim=-1).to(dtype) * self.tile_size


def bin_gaussians(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    tile_size: int = 8,
    conics: Tensor | None = None,
    opacities: Tensor | None = None,
    kernel: Kernel = "auto",
) -> TileBins:
    """Assign every visible Gaussian to the tiles it can reach.

    means2d: [N, 2] pixels; radii: [N, 2] per-axis half extents (0 = culled); depths: [N];
    conics: [N, 3] and opacities: [N], optional. Candidate tiles are those the bounding box
    [mean - r, mean + r] touches, which contains every pixel centre where the Gaussian can reach
    alpha >= 1/255. With conics and opacities, the box first shrinks to the ellipse where
    o exp(-d^T conic d / 2) >= 1/255 (gsplat's opacity-aware extent), and then candidates whose
    pixel centres all stay below 1/255 (box corners, thin tilted ellipses, faint Gaussians) are
    dropped: about a quarter of the pairs on typical scenes, and no visible contribution is lost.
    kernel: "auto" | "cpp" | "torch" (see ``eva_engine.render.native``); the compiled binning
    needs conics and opacities and gives the same pairs up to the rounding slack of the test.
    """
    device = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    num_tiles = tiles_x * tiles_y
    exact = conics is not None and opacities is not None
    with torch.no_grad():
        if exact and RASTER.resolve(kernel, means2d) == "cpp":
            dt = means2d.dtype
            gauss_ids, tile_ids, tile_start, tile_count = RASTER.load().bin_tiles(
                means2d.detach(),
                conics.detach().to(dt),
                opacities.detach().to(dt),
                radii.to(torch.int32),
                depths.detach().to(dt),
                width,
                height,
                tile_size,
            )
            return TileBins(tile_size, tiles_x, tiles_y, gauss_ids, tile_ids, tile_start, tile_count)
        visible = torch.nonzero((radii > 0).all(dim=-1)).squeeze(-1)
        # Front-to-back order first; the stable sort by tile below keeps it within each tile.
        order = visible[torch.argsort(depths.detach()[visible], stable=True)]
        m = means2d.detach()[order].double()
        r = radii[order].double()
        if exact:
            r = torch.minimum(r, _opacity_extent(conics.detach()[order], opacities.detach()[order]))
        x0 = torch.floor((m[:, 0] - r[:, 0]) / tile_size).clamp(0, tiles_x).long()
        x1 = torch.ceil((m[:, 0] + r[:, 0]) / tile_size).clamp(0, tiles_x).long()
        y0 = torch.floor((m[:, 1] - r[:, 1]) / tile_size).clamp(0, tiles_y).long()
        y1 = torch.ceil((m[:, 1] + r[:, 1]) / tile_size).clamp(0, tiles_y).long()
        span_x = (x1 - x0).clamp_min(0)
        counts = span_x * (y1 - y0).clamp_min(0)
        owner = torch.repeat_interleave(torch.arange(order.shape[0], device=device), counts)
        first = torch.cumsum(counts, 0) - counts
        # One packed gather of the per-Gaussian integers instead of one per array.
        first, span, x0, y0 = torch.stack([first, span_x, x0, y0], -1).index_select(0, owner).unbind(-1)
        local = torch.arange(owner.shape[0], device=device) - first
        tx = x0 + local % span
        ty = y0 + local // span
        if exact and owner.numel():
            keep = _reaches_tile(
                means2d.detach()[order],
                conics.detach()[order],
                opacities.detach()[order],
                owner,
                tx,
                ty,
                tile_size,
                width,
                height,
            )
            keep = torch.nonzero(keep).squeeze(-1)
            owner, tx, ty = owner[keep], tx[keep], ty[keep]
        tile = ty * tiles_x + tx
        tile_ids, perm = torch.sort(tile, stable=True)
        gauss_ids = order[owner[perm]]
        tile_count = torch.bincount(tile_ids, minlength=num_tiles)
        tile_start = torch.cumsum(tile_count, 0) - tile_count
    return TileBins(tile_size, tiles_x, tiles_y, gauss_ids, tile_ids, tile_start, tile_count)


def _opacity_extent(conics: Tensor, opacities: Tensor) -> Tensor:
    """[G, 2] float64 per-axis half extents of the ellipse where o exp(-q / 2) >= 1/255.

    q = d^T conic d <= 2 log(255 o) reaches sqrt(2 log(255 o) * Sigma_xx) along x (Sigma =
    conic^-1), i.e. gsplat's opacity-aware radius instead of a fixed 3.33 sigma. The extra pixel
    covers float32 rounding of the conic; a degenerate conic keeps the projection's box (inf).
    """
    a, b, c = conics.double().unbind(-1)
    det = a * c - b * b
    q = 2.0 * torch.log((255.0 * opacities.double()).clamp_min(1.0))
    ok = (det > 0) & torch.isfinite(det)
    det = torch.where(ok, det, torch.ones_like(det))
    ext = torch.stack([(q * c / det).clamp_min(0).sqrt(), (q * a / det).clamp_min(0).sqrt()], -1) + 1.0
    return torch.where(ok[:, None], ext, torch.full_like(ext, math.inf))


def _reaches_tile(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    owner: Tensor,
    tx: Tensor,
    ty: Tensor,
    tile_size: int,
    width: int,
    height: int,
) -> Tensor:
    """[K] bool: Gaussian ``owner`` reaches alpha >= 1/255 at some in-image pixel centre of tile
    (tx, ty). Per-Gaussian inputs [G, ...]; per-candidate owner, tx, ty [K].

    log alpha = log o - q / 2 with q = d^T conic d convex, so over the rectangle of pixel centres
    -q / 2 peaks at the mean when the mean lies inside, and otherwise on an edge, where it is a
    clamped 1D optimum. Tile-local coordinates keep float32 accurate; the slack
    grows with the size of the terms so rounding can only keep a pair, never drop a visible one.
    """
    log_thresh = math.log(1.0 / 255.0) - torch.log(opacities.clamp_min(1e-30))
    table = torch.cat([means2d, conics, log_thresh[:, None]], dim=-1).index_select(0, owner)
    mx, my, a, b, c, thresh = table.unbind(-1)
    mx = mx - tx * tile_size
    my = my - ty * tile_size
    lo = 0.5
    hx = torch.clamp_max(width - 0.5 - tx * tile_size, tile_size - 0.5).to(mx.dtype)
    hy = torch.clamp_max(height - 0.5 - ty * tile_size, tile_size - 0.5).to(my.dtype)

    def value(x: Tensor, y: Tensor) -> Tensor:
        dx, dy = mx - x, my - y
        return -0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy)

    def clip(v: Tensor, high: Tensor) -> Tensor:
        return torch.minimum(v.clamp_min(lo), high)

    lo_t = torch.full_like(mx, lo)
    best = torch.maximum(
        value(lo_t, clip(my + b * (mx - lo) / c, hy)), value(hx, clip(my + b * (mx - hx) / c, hy))
    )
    best = torch.maximum(best, value(clip(mx + b * (my - lo) / a, hx), lo_t))
    best = torch.maximum(best, value(clip(mx + b * (my - hy) / a, hx), hy))
    inside = (mx >= lo) & (mx <= hx) & (my >= lo) & (my <= hy)
    best = torch.where(inside, torch.zeros_like(best), best)
    reach = torch.maximum((mx - lo).abs(), (mx - hx).abs()).maximum(
        torch.maximum((my - lo).abs(), (my - hy).abs())
    )
    slack = 1e-3 + 1e-5 * (a + 2 * b.abs() + c) * reach * reach
    return best >= thresh - slack
