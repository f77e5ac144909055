"""Posing canonical Gaussians by linear blend skinning (EVA §3.1): the functional core.

For Gaussian i with weights w_i [J] and rest->posed joint transforms G_k = [R_k | b_k]:
    A_i = sum_k w_ik [R_k | b_k]        (3x4, the blended transform)
    p_i^f = A_i[:, :3] p_i^c + A_i[:, 3]
    Sigma_i^f = R_i Sigma_i^c R_i^T      with R_i the rotation nearest A_i[:, :3]
The blended 3x3 part of LBS is not a rotation (it shrinks where weights mix distant rotations),
so the covariance is rotated by its Gram-Schmidt orthonormalisation (smooth, finite gradients
even for a degenerate blend) and the quaternions are composed with it: q^f = q(R_i) q^c.

``skin_gaussians`` blends the transforms with one matrix product either way, then runs the rest
in a compiled C++ kernel (``csrc/skinning.cpp``: the same steps in one pass per Gaussian, with a
hand-written backward) where it builds, and in these torch steps elsewhere;
``EVA_SKINNING_KERNEL`` (auto | cpp | torch) or the ``kernel`` argument picks (``eva_engine.native``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import roma
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from eva_engine.native import Kernel, NativeLibrary

ORTHONORMALIZE_EPS = 1e-8
SPARSE_WEIGHT_FLOOR = 1e-6  # ``sparse_weights``: the softmax's floor on a bone is ~1e-8
SKINNING = NativeLibrary(
    "eva_skinning",
    Path(__file__).resolve().parent / "csrc" / "skinning.cpp",
    "EVA_SKINNING_KERNEL",
    "skinning",
)


def blend_transforms(weights: Tensor, transforms: Tensor) -> Tensor:
    """weights: [N, J] (dense, or sparse CSR from ``sparse_weights``); transforms: [J, 4, 4] ->
    blended [N, 3, 4]."""
    j = transforms.shape[0]
    return (weights @ transforms[:, :3, :].reshape(j, 12)).view(-1, 3, 4)


def sparse_weights(weights: Tensor, floor: float = SPARSE_WEIGHT_FLOOR) -> Tensor:
    """[N, J] skinning weights (rows summing to 1) -> the same as a sparse CSR tensor, without
    the entries under ``floor``, rows renormalised: for rendering a trained avatar, whose
    Gaussians each follow a few of the body's bones (the softmax leaves ~1e-8 on each of the
    others), so the blend reads a few entries per row instead of J (``docs/speed.md``). A
    point moves by at most the dropped weight (under J x ``floor``) times the bones' spread.
    Without autograd only (no gradient reaches the dropped entries); a row with no entry over
    ``floor`` keeps its largest."""
    keep = (weights >= floor) | (weights == weights.amax(dim=1, keepdim=True))
    kept = torch.where(keep, weights, torch.zeros_like(weights))
    kept = kept / kept.sum(dim=1, keepdim=True).clamp_min(torch.finfo(kept.dtype).tiny)
    with warnings.catch_warnings():  # "sparse CSR support is in beta": only its matmul is used
        warnings.simplefilter("ignore", UserWarning)
        return kept.to_sparse_csr()


def orthonormalize(m: Tensor, eps: float = ORTHONORMALIZE_EPS) -> Tensor:
    """[N, 3, 3] -> [N, 3, 3] rotations by Gram-Schmidt on the first two columns (eps keeps a
    degenerate column finite)."""
    a1, a2 = m[..., :, 0], m[..., :, 1]
    r1 = a1 / (a1.norm(dim=-1, keepdim=True) + eps)
    a2 = a2 - (r1 * a2).sum(-1, keepdim=True) * r1
    r2 = a2 / (a2.norm(dim=-1, keepdim=True) + eps)
    r3 = torch.cross(r1, r2, dim=-1)
    return torch.stack([r1, r2, r3], dim=-1)


def quat_multiply(q1: Tensor, q2: Tensor) -> Tensor:
    """Hamilton product of [..., 4] (w, x, y, z) quaternions (norms multiply)."""
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def rotmat_to_quat_wxyz(r: Tensor) -> Tensor:
    """[..., 3, 3] rotations -> [..., 4] unit quaternions (w, x, y, z)."""
    return roma.quat_xyzw_to_wxyz(roma.rotmat_to_unitquat(r))


def skin_gaussians(
    means: Tensor, quats: Tensor, weights: Tensor, transforms: Tensor, kernel: Kernel = "auto"
) -> tuple[Tensor, Tensor, Tensor]:
    """Pose canonical Gaussians.

    means: [N, 3]; quats: [N, 4] (w, x, y, z, any norm: it is kept, so a zero quaternion stays
    zero, which the rasterizer reads as identity); weights: [N, J]; transforms: [J, 4, 4].
    Returns posed means [N, 3], posed quats [N, 4] and the per-Gaussian rotations [N, 3, 3]
    (canonical -> posed; e.g. to bring view directions into canonical space for SH colours).
    kernel: "auto" | "cpp" | "torch" (module docstring); differentiable either way.
    """
    a = blend_transforms(weights, transforms)
    if SKINNING.resolve(kernel, means) == "cpp" and quats.dtype == a.dtype == means.dtype:
        return _SkinCompiled.apply(means, quats, a.reshape(-1, 12), SKINNING.load())
    posed = (a[:, :, :3] @ means.unsqueeze(-1)).squeeze(-1) + a[:, :, 3]
    rot = orthonormalize(a[:, :, :3])
    return posed, quat_multiply(rotmat_to_quat_wxyz(rot), quats), rot


class _SkinCompiled(torch.autograd.Function):
    """``skin_gaussians`` after the blend in the compiled kernel: the same outputs, gradients by
    hand. blended: [N, 12] the row-major 3x4 blended transforms."""

    @staticmethod
    def forward(ctx, means, quats, blended, ops):
        ctx.save_for_backward(means, quats, blended)
        ctx.ops = ops
        return ops.skin_forward(means, quats, blended, ORTHONORMALIZE_EPS)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_means, grad_quats, grad_rots):
        means, quats, blended = ctx.saved_tensors
        grads = ctx.ops.skin_backward(
            means, quats, blended, ORTHONORMALIZE_EPS, grad_means, grad_quats, grad_rots
        )
        return (*(g if need else None for g, need in zip(grads, ctx.needs_input_grad, strict=False)), None)
