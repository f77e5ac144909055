"""Real spherical harmonics colours, degree 0-3, with the 3DGS constants and conventions.

``eval_sh`` runs the rasterizer's compiled kernel (``csrc/raster.cpp``, the same polynomials
with a hand-written backward) where it loads, else these torch steps (``native``).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from eva_engine.geometry import camera_center
from eva_engine.render.native import RASTER, Kernel

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Coefficients per colour channel for an SH degree: (degree + 1)^2."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """[N, 3] unit directions -> [N, (degree + 1)^2] real SH basis values (3DGS order and signs)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, sh_coeffs: Tensor, dirs: Tensor, kernel: Kernel = "auto") -> Tensor:
    """View-dependent colour as 3DGS renders it: max(sum_k Y_k(dir) c_k + 0.5, 0).

    sh_coeffs: [N, K, 3] with K >= (degree + 1)^2 (extra coefficients are ignored);
    dirs: [N, 3] viewing directions (camera -> Gaussian), any length (normalised here; a zero
    direction only affects degree >= 1 terms, which it zeroes). Returns [N, 3].
    The +0.5 offset makes an all-zero coefficient set mid-grey (``rgb_to_sh`` inverts the DC
    term); the clamp keeps colours non-negative, as in 3DGS. kernel: "auto" | "cpp" | "torch"
    (``eva_engine.render.native``).
    """
    k = num_sh_bases(degree)
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    if sh_coeffs.shape[-2] < k:
        raise ValueError(f"SH degree {degree} needs {k} coefficients, got {sh_coeffs.shape[-2]}")
    if (
        sh_coeffs.dim() == 3
        and dirs.dim() == 2
        and sh_coeffs.dtype == dirs.dtype
        and dirs.device == sh_coeffs.device
        and RASTER.resolve(kernel, dirs) == "cpp"
    ):
        return _SHCompiled.apply(degree, sh_coeffs, dirs, RASTER.load())
    norm = dirs.norm(dim=-1, keepdim=True)
    unit = dirs / torch.where(norm > 0, norm, torch.ones_like(norm))
    basis = sh_basis(degree, unit)
    rgb = (basis[..., None] * sh_coeffs[..., :k, :]).sum(dim=-2)
    return torch.clamp_min(rgb + 0.5, 0.0)


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """[..., 3] colours -> DC coefficients [..., 3] such that degree-0 ``eval_sh`` returns them."""
    return (rgb - 0.5) / SH_C0


def view_dirs(means: Tensor, viewmat: Tensor) -> Tensor:
    """[N, 3] world means -> [N, 3] unnormalised directions from the camera centre to them."""
    return means - camera_center(viewmat).to(means)


class _SHCompiled(torch.autograd.Function):
    """``eval_sh`` in the compiled kernel: the same colours, gradients by hand."""

    @staticmethod
    def forward(ctx, degree, sh_coeffs, dirs, ops):
        ctx.save_for_backward(sh_coeffs, dirs)
        ctx.degree, ctx.ops = degree, ops
        return ops.sh_forward(degree, sh_coeffs, dirs)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_rgb):
        sh_coeffs, dirs = ctx.saved_tensors
        g_coeffs, g_dirs = ctx.ops.sh_backward(ctx.degree, sh_coeffs, dirs, grad_rgb)
        return None, g_coeffs, g_dirs, None
