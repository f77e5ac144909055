"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (gsplat "classic" semantics).

The maths here is plain differentiable torch: autograd carries gradients from the 2D Gaussians
back to means, quaternions and scales. The compiled kernels (``native``) implement the same
steps in one fused pass with a hand-written backward; ``project_gaussians(kernel=...)`` picks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from eva_engine.geometry import to_camera
from eva_engine.render.native import RASTER, Kernel

# A Gaussian's 2D extent along each screen axis is ceil(RADIUS_SIGMAS * sigma_axis) pixels. 3.33
# sigma is where o * exp(-d^2 / 2) drops below 1/255 even at o = 1, so nothing visible is cut.
RADIUS_SIGMAS = 3.33
# The Jacobian is evaluated at a point clamped to 1.3x the half field of view (3DGS): points far
# outside the frustum would otherwise get a wildly wrong first-order footprint.
FRUSTUM_CLAMP = 1.3
_QUAT_EPS = 1e-12


@dataclass
class Projection:
    """Screen-space 2D Gaussians, one per input Gaussian (culled ones have ``radii == 0``).

    means2d: [N, 2] centres in pixels (pixel (x, y) has its centre at (x + 0.5, y + 0.5)).
    conics:  [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
    depths:  [N] camera-space z (metres along the optical axis).
    radii:   [N, 2] int32 per-axis bounding-box half extents in pixels; 0 = culled.
    compensations: [N] sqrt(det(cov2d - eps2d I) / det(cov2d)) in [0, 1]: the opacity factor of
             gsplat's "antialiased" mode, which keeps a Gaussian's 2D mass as eps2d widens it.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    compensations: Tensor

    @property
    def visible(self) -> Tensor:
        """[N] bool: the Gaussian survived culling."""
        return (self.radii > 0).all(dim=-1)


def normalize_quats(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z) -> unit quaternions; a (near-)zero quaternion becomes the identity.

    The zero quaternion has no direction, so it is defined as "no rotation" with zero gradient
    instead of producing NaNs from 0/0.
    """
    norm = quats.norm(dim=-1, keepdim=True)
    ok = norm > _QUAT_EPS
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    return torch.where(ok, quats / torch.where(ok, norm, torch.ones_like(norm)), identity)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3] rotation matrices (see ``normalize_quats``)."""
    w, x, y, z = normalize_quats(quats).unbind(-1)
    # The nine entries laid out as the 3x3 matrix they form.
    # fmt: off
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*quats.shape[:-1], 3, 3)
    # fmt: on


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    kernel: Kernel = "auto",
) -> Projection:
    """Project 3D Gaussians with the first-order (EWA) approximation of the pinhole camera.

    means: [N, 3] world positions; quats: [N, 4] (w, x, y, z); scales: [N, 3] linear std-devs;
    viewmat: [4, 4] world->camera (OpenCV: x right, y down, z forward); K: [3, 3] intrinsics.

    Culling (radii = 0): camera z outside [near_plane, far_plane], a non-positive 2D covariance
    determinant, or a 2D bounding box entirely outside the image.

    kernel: "auto" | "cpp" | "torch" (see ``eva_engine.render.native``). The compiled kernel
    differentiates w.r.t. means, quats and scales; with a camera that requires grad, or on other
    devices and dtypes, the torch version runs.
    """
    camera_grad = (torch.is_tensor(viewmat) and viewmat.requires_grad) or (
        torch.is_tensor(K) and K.requires_grad
    )
    if not camera_grad and RASTER.resolve(kernel, means) == "cpp":
        means2d, conics, depths, compensations, radii = _ProjectCompiled.apply(
            means, quats, scales, viewmat, K, width, height, near_plane, far_plane, eps2d, RASTER.load()
        )
        return Projection(means2d, conics, depths, radii, compensations)
    dtype = means.dtype
    viewmat = viewmat.to(device=means.device, dtype=dtype)
    rot_w = viewmat[:3, :3]
    p_cam = to_camera(means, viewmat)
    x, y, z = p_cam.unbind(-1)
    in_range = (z >= near_plane) & (z <= far_plane)
    # Culled points still run through the maths; a safe z keeps their (unused) values and
    # gradients finite, so 0 * inf never turns into NaN in the backward pass.
    z = torch.where(in_range, z, torch.ones_like(z))

    K = K.to(device=means.device, dtype=dtype)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u, v = x / z, y / z
    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)

    # gsplat's frustum clamp; for a centred principal point it is the 3DGS +-1.3 * tan(fov / 2).
    margin = FRUSTUM_CLAMP - 1.0
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    uc = torch.minimum(torch.maximum(u, -(cx / fx + margin * tan_x)), (width - cx) / fx + margin * tan_x)
    vc = torch.minimum(torch.maximum(v, -(cy / fy + margin * tan_y)), (height - cy) / fy + margin * tan_y)
    zeros = torch.zeros_like(z)
    jac = torch.stack([fx / z, zeros, -fx * uc / z, zeros, fy / z, -fy * vc / z], dim=-1).reshape(-1, 2, 3)

    # cov2d = A A^T + eps2d I with A = J W R S. Its determinant via Cauchy-Binet (sum of squared
    # 2x2 minors of A) is non-negative by construction, unlike a*c - b^2, which cancels
    # catastrophically in float32 for needle-like Gaussians. A avoids N tiny batched matmuls
    # (slow on CPU): W R as one [3N, 3] GEMM, then J (.) as a sum over J's three columns.
    basis = (quat_to_rotmat(quats).transpose(1, 2) @ rot_w.T).transpose(1, 2) * scales[:, None, :]
    A = (
        jac[:, :, 0:1] * basis[:, None, 0]
        + jac[:, :, 1:2] * basis[:, None, 1]
        + jac[:, :, 2:3] * basis[:, None, 2]
    )
    m00 = (A[:, 0] * A[:, 0]).sum(-1)
    m01 = (A[:, 0] * A[:, 1]).sum(-1)
    m11 = (A[:, 1] * A[:, 1]).sum(-1)
    minor01 = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    minor02 = A[:, 0, 0] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 0]
    minor12 = A[:, 0, 1] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 1]
    a, b, c = m00 + eps2d, m01, m11 + eps2d
    det = minor01**2 + minor02**2 + minor12**2 + eps2d * (m00 + m11) + eps2d**2
    det_ok = det > 0
    det = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    # sqrt(det(A A^T) / det(cov2d)) with gsplat's gradient d sqrt(r) = dr / (2 (sqrt(r) + 1e-6)),
    # as the compiled kernel has it: finite where a needle or a point makes r = 0.
    ratio = ((minor01**2 + minor02**2 + minor12**2) / det).clamp_min(0)
    root = ratio.detach().sqrt()
    compensations = root + (ratio - ratio.detach()) * (0.5 / (root + 1e-6))

    with torch.no_grad():
        rx = torch.ceil(RADIUS_SIGMAS * a.clamp_min(0).sqrt())
        ry = torch.ceil(RADIUS_SIGMAS * c.clamp_min(0).sqrt())
        mx, my = means2d.unbind(-1)
        on_image = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        keep = in_range & det_ok & (rx > 0) & (ry > 0) & on_image
        keep &= torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1)
        # Clamp before the int cast: a Gaussian at the near plane can be 1e9 pixels wide.
        radii = torch.stack([rx, ry], dim=-1).clamp_max(2**30).to(torch.int32)
        radii = torch.where(keep[:, None], radii, torch.zeros_like(radii))
    return Projection(means2d, conics, p_cam[:, 2], radii, compensations)


class _ProjectCompiled(torch.autograd.Function):
    """``project_gaussians`` in the compiled kernels: the same outputs, gradients by hand."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far, eps2d, ops):
        viewmat = torch.as_tensor(viewmat).detach().to("cpu", torch.float64)
        K = torch.as_tensor(K).detach().to("cpu", torch.float64)
        camera = (viewmat, K, width, height, float(near), float(far), float(eps2d))
        means2d, conics, depths, compensations, radii = ops.project_forward(means, quats, scales, *camera)
        ctx.save_for_backward(means, quats, scales)
        ctx.camera, ctx.ops = camera, ops
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, compensations, radii

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_means2d, grad_conics, grad_depths, grad_compensations, _grad_radii):
        means, quats, scales = ctx.saved_tensors
        g_means, g_quats, g_scales = ctx.ops.project_backward(
            means, quats, scales, *ctx.camera, grad_means2d, grad_conics, grad_depths, grad_compensations
        )
        return g_means, g_quats, g_scales, *([None] * 8)
