"""``rasterize``: 3D Gaussians + one pinhole camera -> image, alpha, depth (gsplat conventions)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from eva_engine.render.composite import (
    CompositeConfig,
    composite_autograd,
    composite_image,
    tiles_to_image,
)
from eva_engine.render.native import KERNELS, Kernel
from eva_engine.render.projection import project_gaussians
from eva_engine.render.sh import eval_sh, view_dirs
from eva_engine.render.tiles import bin_gaussians

RasterizeMode = Literal["classic", "antialiased"]
RASTERIZE_MODES: tuple[str, ...] = ("classic", "antialiased")


@dataclass(frozen=True)
class RasterConfig:
    """How to rasterize (never what): every setting gives the same image up to rounding.

    backend: "tiled" (default): hand-written backward, memory O(pixels + Gaussians);
             "autograd": plain torch autograd through the compositing, memory O(Gaussian-pixel
             pairs); the reference the tests compare against.
    tile_size: square screen tiles in pixels (8 is fastest on CPU).
    kernel: the "tiled" backend's projection, binning and compositing kernels: "cpp" (compiled C++/OpenMP,
            built once per machine), "torch" (pure torch, runs anywhere) or "auto" (default:
            ``EVA_RASTER_KERNEL`` if set, else "cpp" when it builds, for CPU float32/float64);
            see ``eva_engine.render.native``.
    composite: chunking of the torch compositing kernels.
    """

    backend: Literal["tiled", "autograd"] = "tiled"
    tile_size: int = 8
    kernel: Kernel = "auto"
    composite: CompositeConfig = field(default_factory=CompositeConfig)

    def __post_init__(self) -> None:
        if self.backend not in ("tiled", "autograd"):
            raise ValueError(f"backend must be 'tiled' or 'autograd', got {self.backend!r}")
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {self.kernel!r}")
        if self.tile_size < 1:
            raise ValueError(f"tile_size must be positive, got {self.tile_size}")


@dataclass
class RenderOutput:
    """Result of ``rasterize`` for one camera (N Gaussians, D colour channels).

    image:   [H, W, D] sum_i c_i alpha_i T_i + T_final * background.
    alpha:   [H, W, 1] 1 - T_final (accumulated opacity).
    depth:   [H, W, 1] sum_i z_i alpha_i T_i, alpha-blended camera z (not normalised by alpha;
             divide by ``alpha`` for the expected depth of the covered part).
    means2d: [N, 2] projected centres in pixels. It is a non-leaf tensor of the graph with
             ``retain_grad()`` enabled, so after ``backward()`` its ``.grad`` holds dL/dmeans2d in
             units of loss per pixel: the screen-space gradient used for densification.
    radii:   [N] int32 max per-axis bounding-box radius in pixels; 0 = culled (behind the camera,
             outside [near, far], degenerate, or entirely off-image).
    depths:  [N] camera-space z of the centres.
    num_intersections: Gaussian-tile pairs composited (each is tile_size^2 Gaussian-pixel pairs).
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    depths: Tensor
    num_intersections: int


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    sh_degree: int | None = None,
    config: RasterConfig | None = None,
    rasterize_mode: RasterizeMode = "classic",
) -> RenderOutput:
    """Render N 3D Gaussians from one camera, differentiably.

    means: [N, 3] world positions; quats: [N, 4] (w, x, y, z), any norm (zero = identity);
    scales: [N, 3] linear standard deviations; opacities: [N] in [0, 1];
    colors: [N, D] per-Gaussian features (D >= 1), or with ``sh_degree`` set, [N, K, 3] SH
    coefficients evaluated for this view by ``eval_sh`` (3DGS: +0.5, clamped at 0);
    viewmat: [4, 4] world->camera, OpenCV axes (x right, y down, z forward); K: [3, 3] pixels;
    background: [D] colour behind everything, or None for black.

    Semantics follow gsplat's "classic" rasterization: EWA splatting with the first-order
    Jacobian clamped to 1.3x the field of view, eps2d added to the 2D covariance, pixel centres at
    (x + 0.5, y + 0.5), per-axis radius ceil(3.33 sigma), front-to-back compositing by camera z
    with alpha = min(0.999, o exp(-d^T Sigma^-1 d / 2)), pairs below alpha 1/255 skipped, and each
    pixel stopping before the Gaussian that would take its transmittance to <= 1e-4.
    ``rasterize_mode="antialiased"`` is gsplat's mode of that name (Mip-Splatting's 2D filter): each
    opacity times sqrt(det(cov2d - eps2d I) / det(cov2d)), so a Gaussian smaller than a pixel keeps
    its 2D mass instead of growing to eps2d at full opacity. An avatar trained at one image scale
    and seen at another (the face close-ups and the frame) then looks the same in both.

    Differentiable w.r.t. means, quats, scales, opacities, colors and background. Works on any
    device and float dtype the inputs share (float32 normally, float64 for gradient checks).
    A Gaussian with NaN or inf in any of its inputs is not drawn and gets zero gradients, so one
    diverged Gaussian neither blanks the image nor poisons the others' gradients.
    """
    cfg = config or RasterConfig()
    _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree)
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    means, quats, scales, opacities, colors = _drop_non_finite(means, quats, scales, opacities, colors)

    # The autograd reference stays pure torch end to end.
    kernel = cfg.kernel if cfg.backend == "tiled" else "torch"
    proj = project_gaussians(
        means, quats, scales, viewmat, K, width, height, near_plane, far_plane, eps2d, kernel
    )
    means2d = proj.means2d
    if rasterize_mode == "antialiased":
        opacities = opacities * proj.compensations
    if means2d.requires_grad:
        means2d.retain_grad()
    if sh_degree is not None:
        colors = eval_sh(sh_degree, colors, view_dirs(means, viewmat))

    bins = bin_gaussians(
        means2d, proj.radii, proj.depths, width, height, cfg.tile_size, proj.conics, opacities, kernel
    )
    if cfg.backend == "tiled":
        image, depth, alpha = composite_image(
            means2d,
            proj.conics,
            opacities,
            colors,
            proj.depths,
            bins,
            width,
            height,
            background,
            cfg.composite,
            kernel,
        )
    else:
        # Depth is composited as one more feature channel, with no background term.
        feats = torch.cat([colors, proj.depths[:, None]], dim=-1)
        acc, t_final = composite_autograd(means2d, proj.conics, opacities, feats, bins, cfg.composite)
        acc = tiles_to_image(acc, bins, width, height)
        t_final = tiles_to_image(t_final[..., None], bins, width, height)
        image, depth, alpha = acc[..., :-1], acc[..., -1:], 1.0 - t_final
        if background is not None:
            image = image + t_final * background.to(image)
    return RenderOutput(
        image=image,
        alpha=alpha,
        depth=depth,
        means2d=means2d,
        radii=proj.radii.amax(dim=-1),
        depths=proj.depths,
        num_intersections=bins.num_intersections,
    )


def _drop_non_finite(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The inputs with every Gaussian that holds a non-finite value replaced by an invisible one
    (opacity 0 at the origin), through ``torch.where`` so its gradients are zero."""
    with torch.no_grad():  # a row's sum is finite iff all its values are (or sum past 1e38)
        total = means.sum(1) + quats.sum(1) + scales.sum(1) + opacities + colors.flatten(1).sum(1)
        finite = torch.isfinite(total)  # [N]
    if bool(finite.all()):
        return means, quats, scales, opacities, colors

    def keep(t: Tensor, fill: float | Tensor) -> Tensor:
        mask = finite.view(-1, *([1] * (t.dim() - 1)))
        return torch.where(mask, t, torch.as_tensor(fill, dtype=t.dtype, device=t.device))

    identity = quats.new_tensor([1.0, 0.0, 0.0, 0.0])
    return (
        keep(means, 0.0),
        keep(quats, identity),
        keep(scales, 1e-3),
        keep(opacities, 0.0),
        keep(colors, 0.0),
    )


def _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background, sh_degree):
    n = means.shape[0] if means.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    if tuple(quats.shape) != (n, 4):
        raise ValueError(f"quats must be [N, 4] = [{n}, 4], got {tuple(quats.shape)}")
    if tuple(scales.shape) != (n, 3):
        raise ValueError(f"scales must be [N, 3] = [{n}, 3], got {tuple(scales.shape)}")
    if tuple(opacities.shape) != (n,):
        raise ValueError(f"opacities must be [N] = [{n}], got {tuple(opacities.shape)}")
    if sh_degree is None:
        if colors.dim() != 2 or colors.shape[0] != n or colors.shape[1] < 1:
            raise ValueError(f"colors must be [N, D] with N = {n}, D >= 1, got {tuple(colors.shape)}")
        channels = colors.shape[1]
    else:
        if colors.dim() != 3 or colors.shape[0] != n or colors.shape[2] != 3:
            raise ValueError(f"SH colors must be [N, K, 3] with N = {n}, got {tuple(colors.shape)}")
        channels = 3
    if tuple(viewmat.shape) != (4, 4) or tuple(K.shape) != (3, 3):
        raise ValueError(f"viewmat must be [4, 4] and K [3, 3], got {tuple(viewmat.shape)}, {tuple(K.shape)}")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if background is not None and tuple(background.shape) != (channels,):
        raise ValueError(f"background must be [{channels}], got {tuple(background.shape)}")
    tensors = [means, quats, scales, opacities, colors] + ([background] if background is not None else [])
    if len({(t.dtype, t.device) for t in tensors}) != 1 or not means.is_floating_point():
        found = sorted({f"{t.dtype} on {t.device}" for t in tensors})
        raise ValueError(
            f"Gaussian tensors and background must share one float dtype and device, got {found}"
        )
