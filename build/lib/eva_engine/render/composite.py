"""Front-to-back alpha compositing of tile-binned 2D Gaussians.

Inputs are per-Gaussian 2D parameters (means2d, conics, opacities, features) plus their tile
binning; the projection in front of this stage is plain autograd. Each Gaussian-tile intersection
becomes 6 coefficients of a quadratic in the tile-local pixel coordinates (x, y) (pixel centres
at 0.5, 1.5, ...):

    log alpha_raw(x, y) = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2
                        = log(o) - 1/2 d^T conic d,  d = mean - pixel

so a whole [tiles, Gaussians, pixels] block of alphas is one matmul plus one exp, and the
gradients of a block reduce to matmuls with the same pixel basis. Coordinates are local to each
tile to keep the expanded quadratic well conditioned in float32.

Rules (3DGS / gsplat): alpha = min(0.999, alpha_raw); pairs with alpha < 1/255 are skipped; a
pixel stops before the Gaussian that would bring its transmittance to <= 1e-4.

Two implementations share these rules:
- ``composite_image`` (default): a hand-written backward that recomputes alphas back to front
  from the final transmittance and per-pixel contributor count saved by the forward. Memory:
  O(pixels + intersections). Its kernels are either the compiled ones (``csrc/raster.cpp``: one
  thread per tile, pixels vectorised, image layout; see ``native``) or ``composite``, in torch,
  which walks each tile in chunks of ``chunk_size`` Gaussians as batched tensor ops.
- ``composite_autograd``: the same maths in plain differentiable torch, one padded block per
  group of tiles. Memory: O(Gaussian-pixel pairs). It is the reference the tests compare with.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F_nn
from torch import Tensor
from torch.autograd.function import once_differentiable

from eva_engine.render.native import RASTER, Kernel
from eva_engine.render.tiles import TileBins

ALPHA_MAX = 0.999
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
# Log-alpha of padding slots: exp() underflows to exactly 0 in float32 and float64.
_PAD_LOG_ALPHA = -1e4
_MIN_OPACITY = 1e-12
_LOG2E = 1.4426950408889634


def _alpha_min(dtype: torch.dtype) -> float:
    """The largest value below 1/255 in ``dtype``: threshold(x, it) keeps exactly x >= 1/255."""
    t = torch.tensor(ALPHA_MIN, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


@dataclass(frozen=True)
class CompositeConfig:
    """Work partitioning of the torch kernels of the tiled compositor (results do not depend on
    it; the compiled kernels always take one tile at a time).

    chunk_size: Gaussians per tile processed at once (the K of the [tiles, pixels, K] blocks).
    block_elements: upper bound on tiles * pixels * K per block, which bounds working memory.
    """

    chunk_size: int = 32
    block_elements: int = 1 << 18

    def __post_init__(self) -> None:
        if self.chunk_size < 1 or self.block_elements < 1:
            raise ValueError(f"chunk_size and block_elements must be positive, got {self}")


def quadratic_coefs(means_local: Tensor, conics: Tensor, log_opacities: Tensor) -> Tensor:
    """Per-intersection log-alpha quadratic.

    means_local: [M, 2] Gaussian centre relative to the tile's top-left corner (pixels);
    conics: [M, 3] (a, b, c); log_opacities: [M]. Returns [M, 6] (see module docstring).
    """
    mx, my = means_local.unbind(-1)
    a, b, c = conics.unbind(-1)
    return torch.stack(
        [
            log_opacities - 0.5 * (a * mx * mx + c * my * my) - b * mx * my,
            a * mx + b * my,
            b * mx + c * my,
            -0.5 * a,
            -b,
            -0.5 * c,
        ],
        dim=-1,
    )


def pixel_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[P, 6] monomials (1, x, y, x^2, xy, y^2) of the tile-local pixel centres, row-major."""
    r = torch.arange(tile_size, dtype=dtype, device=device) + 0.5
    y, x = torch.meshgrid(r, r, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack([torch.ones_like(x), x, y, x * x, x * y, y * y], dim=-1)


def tiles_to_image(tiles: Tensor, bins: TileBins, width: int, height: int) -> Tensor:
    """[T, P, F] per-tile pixels -> [H, W, F]."""
    s = bins.tile_size
    img = tiles.reshape(bins.tiles_y, bins.tiles_x, s, s, -1).permute(0, 2, 1, 3, 4)
    return img.reshape(bins.tiles_y * s, bins.tiles_x * s, -1)[:height, :width]


def _chunk_slots(bins: TileBins, tiles: Tensor, offsets: Tensor, sentinel: int) -> Tensor:
    """[B] tiles, [C] positions within each tile's depth-sorted list -> [B, C] intersection ids.

    Positions past a tile's end point at ``sentinel`` (a padding row with alpha 0).
    """
    pos = offsets[None, :]
    idx = bins.tile_start[tiles, None] + pos
    return torch.where(pos < bins.tile_count[tiles, None], idx, sentinel)


def _padded(coefs: Tensor, feats: Tensor) -> tuple[Tensor, Tensor]:
    """Append the padding row (alpha = 0, features 0); coefs are rescaled for exp2 (cheaper)."""
    pad = coefs.new_zeros(1, 6)
    pad[0, 0] = _PAD_LOG_ALPHA
    return torch.cat([coefs, pad]) * _LOG2E, torch.cat([feats, feats.new_zeros(1, feats.shape[1])])


def _alpha_block(coef_pad: Tensor, slots: Tensor, basis_t: Tensor) -> Tensor:
    """[B, C] slots -> [B, C, P] unclamped alphas (pixels innermost: one GEMM, no batching)."""
    b, c = slots.shape
    return torch.exp2(coef_pad.index_select(0, slots.reshape(-1)) @ basis_t).reshape(b, c, -1)


def _composite_forward(coefs: Tensor, feats: Tensor, bins: TileBins, cfg: CompositeConfig):
    """Returns acc [T, P, F], final transmittance [T, P] and contributor count [T, P].

    The count (stored as a float) is the number of list entries each pixel walked before it
    stopped; the backward pass uses it to replay exactly the same termination. Per-tile state is
    kept compact for the tiles still active (more Gaussians, not all pixels stopped) so blocks
    are slices, not gathers.
    """
    n_tiles, s, C = bins.num_tiles, bins.tile_size, cfg.chunk_size
    P, F = s * s, feats.shape[1]
    M = coefs.shape[0]
    dev, dt = coefs.device, coefs.dtype
    basis_t = pixel_basis(s, dt, dev).T.contiguous()  # [6, P]
    coef_pad, feat_pad = _padded(coefs, feats)
    alpha_min = _alpha_min(dt)
    per_block = max(1, cfg.block_elements // (P * C))
    arange_c = torch.arange(C, device=dev)

    acc_out = torch.zeros(n_tiles, F, P, dtype=dt, device=dev)
    t_out = torch.ones(n_tiles, P, dtype=dt, device=dev)
    count_out = torch.zeros(n_tiles, P, dtype=dt, device=dev)
    active = torch.nonzero(bins.tile_count > 0).squeeze(-1)
    a = active.shape[0]
    acc = torch.zeros(a, F, P, dtype=dt, device=dev)
    t_run = torch.ones(a, P, dtype=dt, device=dev)  # 0 once a pixel has stopped
    t_stop = torch.ones(a, P, dtype=dt, device=dev)  # transmittance where it stopped
    count = torch.zeros(a, P, dtype=dt, device=dev)
    level = 0
    while a:
        slots = _chunk_slots(bins, active, arange_c + level * C, M)  # [A, C]
        for b0 in range(0, a, per_block):
            blk = slice(b0, min(b0 + per_block, a))
            t0 = t_run[blk]  # [B, P]
            alpha = _alpha_block(coef_pad, slots[blk], basis_t).clamp_max_(ALPHA_MAX)  # [B, C, P]
            alpha = F_nn.threshold(alpha, alpha_min, 0.0)  # keeps alpha >= 1/255
            one_minus = torch.rsub(alpha, 1.0)
            # Transmittance after each Gaussian; a stopped pixel (t0 = 0) includes nothing.
            t_after = torch.cumprod(one_minus, dim=1).mul_(t0[:, None, :])
            # Zero from the first Gaussian that takes T to <= 1e-4 on (T is non-increasing).
            t_kept = F_nn.threshold(t_after, T_MIN, 0.0)
            weights = alpha.mul_(t_kept).div_(one_minus)  # alpha_i T_i, 0 once stopped
            feat_blk = feat_pad.index_select(0, slots[blk].reshape(-1)).reshape(-1, C, F)
            acc[blk] += torch.bmm(feat_blk.transpose(1, 2), weights)
            last = t_kept[:, -1]  # T after the chunk; 0 for pixels that have stopped
            stopped = (last == 0) & (t0 > 0)
            if bool(stopped.any()):  # only then find where inside the chunk they stopped
                n = torch.sign(t_kept).sum(dim=1)  # [B, P] entries walked in this chunk
                t_last = t_after.gather(1, (n - 1).clamp_min(0).long()[:, None, :]).squeeze(1)
                t_stop[blk] = torch.where(stopped, torch.where(n > 0, t_last, t0), t_stop[blk])
                count[blk] += n
            else:
                count[blk] += torch.sign(t0) * C
            t_run[blk] = last
        level += 1
        keep = (bins.tile_count[active] > level * C) & (t_run > 0).any(dim=-1)
        if not bool(keep.all()):
            gone = torch.nonzero(~keep).squeeze(-1)
            done = active[gone]
            acc_out[done] = acc[gone]
            t_out[done] = torch.where(t_run[gone] > 0, t_run[gone], t_stop[gone])
            count_out[done] = count[gone]
            keep = torch.nonzero(keep).squeeze(-1)
            active, acc, t_run, t_stop, count = (x[keep] for x in (active, acc, t_run, t_stop, count))
            a = active.shape[0]
    return acc_out.transpose(1, 2).contiguous(), t_out, count_out


def _composite_backward(
    coefs: Tensor,
    feats: Tensor,
    bins: TileBins,
    cfg: CompositeConfig,
    t_final: Tensor,
    count: Tensor,
    grad_acc: Tensor,
    grad_t: Tensor,
):
    """Gradients of coefs [M, 6] and feats [M, F] given dL/dacc [T, P, F] and dL/dT_final [T, P].

    Per pixel, with T_i the transmittance in front of Gaussian i, h_i = dL/dacc . f_i and
    G_i = sum_{j>=i} alpha_j T_j h_j + dL/dT_final * T_final (Gaussian i and everything behind):
        dL/dalpha_i = (T_i h_i - G_i) / (1 - alpha_i),   dL/df_i = alpha_i T_i dL/dacc.
    Chunks are visited back to front, recovering T_i = T_end / prod_{j>=i} (1 - alpha_j) from the
    saved final transmittance, so nothing per pair is stored between the passes. Tiles are
    ordered by how many chunks they need, so the tiles live at each chunk level are a prefix.
    """
    s, C = bins.tile_size, cfg.chunk_size
    P, F = s * s, feats.shape[1]
    M = coefs.shape[0]
    dev, dt = coefs.device, coefs.dtype
    basis_t = pixel_basis(s, dt, dev).T.contiguous()  # [6, P]
    coef_pad, feat_pad = _padded(coefs, feats)
    alpha_min = _alpha_min(dt)
    grad_coef = torch.zeros(M + 1, 6, dtype=dt, device=dev)
    grad_feat = torch.zeros(M + 1, F, dtype=dt, device=dev)
    per_block = max(1, cfg.block_elements // (P * C))

    # Chunks a tile needs: up to its list length and to the deepest entry any pixel used.
    depth_used = torch.minimum(bins.tile_count, count.amax(dim=-1).long())
    levels = (depth_used + C - 1) // C
    order = torch.argsort(levels, descending=True, stable=True)
    order = order[levels[order] > 0]
    levels = levels[order]
    if order.numel() == 0:
        return grad_coef[:M], grad_feat[:M]
    t_end = t_final[order].clone()
    behind = (grad_t * t_final)[order]
    cnt = count[order]
    g_all = grad_acc[order].transpose(1, 2).contiguous()  # [A, F, P]
    cnt_min = cnt.amin(dim=-1)
    clamp_odds = torch.tensor(ALPHA_MAX, dtype=dt)
    clamp_neg_odds = float(-clamp_odds / (1 - clamp_odds))
    reversed_c = torch.arange(C - 1, -1, -1, device=dev)

    for level in range(int(levels[0]) - 1, -1, -1):
        offsets = reversed_c + level * C  # back to front within the chunk
        n_live = int((levels > level).sum())
        slots = _chunk_slots(bins, order[:n_live], offsets, M)
        offsets_f = offsets.to(dt)[None, :, None]
        for b0 in range(0, n_live, per_block):
            blk = slice(b0, min(b0 + per_block, n_live))
            sl = slots[blk]
            raw = F_nn.threshold(_alpha_block(coef_pad, sl, basis_t), alpha_min, 0.0)  # [B, C, P]
            if bool((cnt_min[blk] < (level + 1) * C).any()):
                # 1 where the forward pass reached this entry, else 0 (count - position, clamped).
                raw.mul_((cnt[blk][:, None, :] - offsets_f).clamp_(0.0, 1.0))
            alpha = raw.clamp_max(ALPHA_MAX)
            one_minus = torch.rsub(alpha, 1.0)
            suffix = torch.cumprod(one_minus, dim=1)  # prod_{j>=i} (1 - alpha_j), back to front
            t_before = t_end[blk][:, None, :] / suffix  # T_i
            g = g_all[blk]  # [B, F, P]
            f = feat_pad.index_select(0, sl.reshape(-1)).reshape(-1, C, F)
            h = torch.bmm(f, g)  # [B, C, P]
            weights = alpha * t_before
            g_incl = torch.cumsum(weights * h, dim=1).add_(behind[blk][:, None, :])
            t_end[blk] /= suffix[:, -1]
            behind[blk] = g_incl[:, -1]
            # dL/dlog-alpha = dL/dalpha * alpha = (T_i h_i - G_i) * alpha / (1 - alpha), and 0 where
            # alpha is clamped at 0.999 (skipped entries have alpha = 0 already). The clamped ones
            # are exactly those whose odds alpha / (1 - alpha) reach the clamp's odds.
            neg_odds = F_nn.threshold(alpha.div_(one_minus).neg_(), clamp_neg_odds, 0.0)
            d_log = g_incl.sub_(t_before.mul_(h)).mul_(neg_odds)
            flat = sl.reshape(-1)
            grad_coef.index_copy_(0, flat, (basis_t @ d_log.reshape(-1, P).T).T)
            grad_feat.index_copy_(0, flat, torch.bmm(weights, g.transpose(1, 2)).reshape(-1, F))
    # Row M collected the padding slots (written in arbitrary order); drop it.
    return grad_coef[:M], grad_feat[:M]


def _log_opacities(opacities: Tensor) -> Tensor:
    # Opacities below 1e-12 give alpha < 1/255 everywhere; the floor keeps log() finite.
    return torch.log(opacities.clamp_min(_MIN_OPACITY))


def _gather(means2d: Tensor, conics: Tensor, opacities: Tensor, feats: Tensor, bins: TileBins):
    """Per-intersection tile-local means [M, 2], conics [M, 3], log-opacities [M], feats [M, F].

    One packed gather (and, in the backward, one packed index_add) instead of one per input.
    """
    table = torch.cat([means2d, conics, _log_opacities(opacities)[:, None], feats], dim=-1)
    rows = table.index_select(0, bins.gauss_ids)
    means_local = rows[:, :2] - bins.tile_origins(bins.tile_ids, rows.dtype)
    return means_local, rows[:, 2:5], rows[:, 5], rows[:, 6:]


def intersection_inputs(
    means2d: Tensor, conics: Tensor, opacities: Tensor, feats: Tensor, bins: TileBins
) -> tuple[Tensor, Tensor]:
    """Per-Gaussian 2D inputs -> per-intersection coefs [M, 6] and features [M, F] (differentiable)."""
    means_local, conics_m, log_opac, feats_m = _gather(means2d, conics, opacities, feats, bins)
    return quadratic_coefs(means_local, conics_m, log_opac), feats_m


def _coef_chain(grad_coef: Tensor, means_local: Tensor, conics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Chain dL/dcoefs [M, 6] to the tile-local means [M, 2], conics [M, 3] and log-opacities [M]."""
    g0, g1, g2, g3, g4, g5 = grad_coef.unbind(-1)
    mx, my = means_local.unbind(-1)
    a, b, c = conics.unbind(-1)
    g_mx = g1 * a + g2 * b - g0 * (a * mx + b * my)
    g_my = g1 * b + g2 * c - g0 * (b * mx + c * my)
    g_a = g1 * mx - 0.5 * (g0 * mx * mx + g3)
    g_b = g1 * my + g2 * mx - g0 * mx * my - g4
    g_c = g2 * my - 0.5 * (g0 * my * my + g5)
    return torch.stack([g_mx, g_my], -1), torch.stack([g_a, g_b, g_c], -1), g0


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, bins, cfg):
        coefs, rows = intersection_inputs(means2d, conics, opacities, feats, bins)
        acc, t_final, count = _composite_forward(coefs, rows, bins, cfg)
        ctx.save_for_backward(means2d, conics, opacities, feats, t_final, count)
        ctx.bins, ctx.cfg = bins, cfg
        ctx.mark_non_differentiable(count)
        return acc, t_final, count

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_acc, grad_t, _grad_count):
        means2d, conics, opacities, feats, t_final, count = ctx.saved_tensors
        bins = ctx.bins
        means_local, conics_m, log_opac, feats_m = _gather(means2d, conics, opacities, feats, bins)
        coefs = quadratic_coefs(means_local, conics_m, log_opac)
        grad_coef, grad_feat = _composite_backward(
            coefs, feats_m, bins, ctx.cfg, t_final, count, grad_acc, grad_t
        )
        # The gather's backward by hand: one packed index_add onto the Gaussians.
        g_mean, g_conic, g_logo = _coef_chain(grad_coef, means_local, conics_m)
        g_rows = torch.cat([g_mean, g_conic, g_logo[:, None], grad_feat], dim=-1)
        g_table = g_rows.new_zeros(means2d.shape[0], g_rows.shape[1]).index_add_(0, bins.gauss_ids, g_rows)
        g_logo = g_table[:, 5]
        g_opac = torch.where(opacities > _MIN_OPACITY, g_logo / opacities.clamp_min(_MIN_OPACITY), 0.0)
        return g_table[:, :2], g_table[:, 2:5], g_opac, g_table[:, 6:], None, None


class _CompositeImage(torch.autograd.Function):
    """The compiled kernels, straight to image layout with the background blended in."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, bins, width, height, ops):
        tiles = (
            bins.gauss_ids,
            bins.tile_start,
            bins.tile_count,
            bins.tiles_x,
            bins.tile_size,
            width,
            height,
        )
        image, depth, alpha, t_final, count = ops.composite_image_forward(
            means2d, conics, opacities, colors, depths, background, *tiles
        )
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, background, t_final, count)
        ctx.tiles, ctx.ops = tiles, ops
        return image, depth, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_image, grad_depth, grad_alpha):
        means2d, conics, opacities, colors, depths, background, t_final, count = ctx.saved_tensors
        # g: [N, 7 + D] = dL/d(means2d x, y | conic a, b, c | opacity | colours | depth) per Gaussian.
        g, g_bg = ctx.ops.composite_image_backward(
            means2d,
            conics,
            opacities,
            colors,
            depths,
            background,
            *ctx.tiles,
            t_final,
            count,
            grad_image,
            grad_depth,
            grad_alpha,
        )
        d = colors.shape[1]
        return g[:, :2], g[:, 2:5], g[:, 5], g[:, 6 : 6 + d], g[:, 6 + d], g_bg, None, None, None, None


def composite_image(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    bins: TileBins,
    width: int,
    height: int,
    background: Tensor | None = None,
    cfg: CompositeConfig | None = None,
    kernel: Kernel = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """Tiled compositing of N 2D Gaussians into an image, with a hand-written backward.

    means2d: [N, 2] pixels; conics: [N, 3]; opacities: [N]; colors: [N, D]; depths: [N] camera z;
    bins: their tile binning; background: [D] or None (black). Returns image [H, W, D] =
    sum_i alpha_i T_i c_i + T_final * background, depth [H, W, 1] = sum_i alpha_i T_i z_i and
    alpha [H, W, 1] = 1 - T_final. kernel: "auto" | "cpp" | "torch" picks the implementation
    (see ``eva_engine.render.native``): the compiled kernels write this layout directly; the
    torch kernels run ``composite`` on colours and depth as one feature block, then untile.
    """
    if RASTER.resolve(kernel, means2d) == "cpp":
        bg = colors.new_zeros(colors.shape[1]) if background is None else background.to(colors)
        return _CompositeImage.apply(
            means2d, conics, opacities, colors, depths, bg, bins, width, height, RASTER.load()
        )
    feats = torch.cat([colors, depths[:, None]], dim=-1)  # depth: one more channel, no background
    acc, t_final = composite(means2d, conics, opacities, feats, bins, cfg)
    acc = tiles_to_image(acc, bins, width, height)
    t_final = tiles_to_image(t_final[..., None], bins, width, height)
    image = acc[..., :-1]
    if background is not None:
        image = image + t_final * background.to(image)
    return image, acc[..., -1:], 1.0 - t_final


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    bins: TileBins,
    cfg: CompositeConfig | None = None,
) -> tuple[Tensor, Tensor]:
    """Tiled compositing of N 2D Gaussians with a hand-written backward, in torch kernels.

    means2d: [N, 2] pixels; conics: [N, 3]; opacities: [N]; feats: [N, F] (colours, depth, ...);
    bins: their tile binning. Returns acc [T, P, F] = sum_i alpha_i T_i f_i per tile pixel and
    the final transmittance [T, P] (T tiles of P = tile_size^2 pixels, see ``tiles_to_image``).
    ``composite_image`` is the entry point that also runs the compiled kernels.
    """
    acc, t_final, _ = _Composite.apply(means2d, conics, opacities, feats, bins, cfg or CompositeConfig())
    return acc, t_final


def composite_autograd(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    bins: TileBins,
    cfg: CompositeConfig | None = None,
) -> tuple[Tensor, Tensor]:
    """Reference compositing in plain autograd; same inputs and outputs as ``composite``.

    Tiles are grouped by intersection count and each group is padded to its longest list, so
    the cumulative product runs over a tile's whole list at once (no chunk carry).
    """
    cfg = cfg or CompositeConfig()
    coefs, feats = intersection_inputs(means2d, conics, opacities, feats, bins)
    n_tiles, s = bins.num_tiles, bins.tile_size
    P, F = s * s, feats.shape[1]
    M = coefs.shape[0]
    dev, dt = coefs.device, coefs.dtype
    basis = pixel_basis(s, dt, dev)
    pad_row = torch.zeros(1, 6, dtype=dt, device=dev)
    pad_row[0, 0] = _PAD_LOG_ALPHA
    coef_pad = torch.cat([coefs, pad_row])
    feat_pad = torch.cat([feats, feats.new_zeros(1, F)])

    used = torch.nonzero(bins.tile_count > 0).squeeze(-1)
    used = used[torch.argsort(bins.tile_count[used], descending=True)]
    counts = bins.tile_count[used].tolist()
    done_tiles, acc_parts, t_parts = [], [], []
    start = 0
    while start < len(counts):
        k = counts[start]
        stop = start + max(1, cfg.block_elements // (P * k))
        tiles = used[start:stop]
        slots = _chunk_slots(bins, tiles, torch.arange(k, device=dev), M)
        alpha = torch.exp(torch.matmul(basis, coef_pad[slots].transpose(1, 2))).clamp(max=ALPHA_MAX)
        alpha = torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha), alpha)
        t_after = torch.cumprod(1.0 - alpha, dim=-1)
        included = t_after > T_MIN
        t_before = torch.cat([torch.ones_like(t_after[..., :1]), t_after[..., :-1]], dim=-1)
        weights = torch.where(included, alpha * t_before, torch.zeros_like(alpha))
        n = included.sum(-1, keepdim=True)
        t_last = t_after.gather(-1, (n - 1).clamp_min(0)).squeeze(-1)
        acc_parts.append(torch.bmm(weights, feat_pad[slots]))
        t_parts.append(torch.where(n.squeeze(-1) > 0, t_last, torch.ones_like(t_last)))
        done_tiles.append(tiles)
        start = stop
    acc = coefs.new_zeros(n_tiles, P, F)
    t_final = coefs.new_ones(n_tiles, P)
    if done_tiles:
        tiles = torch.cat(done_tiles)
        acc = acc.index_put((tiles,), torch.cat(acc_parts))
        t_final = t_final.index_put((tiles,), torch.cat(t_parts))
    return acc, t_final
