"""Small geometry the engine shares: points into a camera's frame and onto its image, a camera's
centre, and a triangle mesh's vertex normals.

Conventions (``eva_engine.render.camera``): OpenCV camera axes (x right, y down, z forward),
``viewmat`` [4, 4] world->camera, ``K`` [3, 3] in pixels; pixel (x, y) spans [x, x+1) x [y, y+1),
so ``floor`` of a projected point is the pixel it falls in.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

MIN_DEPTH = 0.05
"""Metres: ``project_points`` clamps depth here, nearer than any camera films a person, so a point
at or behind the camera projects to finite (far-off) pixels."""


def to_camera(points: Tensor, viewmat: Tensor) -> Tensor:
    """points [..., N, 3] world, viewmat [4, 4] or [B, 4, 4] (then points [B, N, 3]) ->
    [..., N, 3] camera coordinates."""
    return points @ viewmat[..., :3, :3].transpose(-1, -2) + viewmat[..., None, :3, 3]


def project_points(points_cam: Tensor, K: Tensor, min_depth: float = MIN_DEPTH) -> Tensor:
    """[..., N, 3] camera coordinates -> [..., N, 2] pixels through K [3, 3] or [B, 3, 3] (then
    points [B, N, 3]), skew included. Depth is clamped at ``min_depth``: a point at or behind the
    camera stays finite (in fitting, its residual is large and bounded by the robust loss)."""
    z = points_cam[..., 2:3].clamp_min(min_depth)
    xy = points_cam[..., :2] / z
    x, y = xy[..., 0], xy[..., 1]
    K = K[..., None, :, :]  # one K for every point of its batch
    u = K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2]
    v = K[..., 1, 1] * y + K[..., 1, 2]
    return torch.stack([u, v], dim=-1)


def camera_center(viewmat: Tensor) -> Tensor:
    """[..., 4, 4] world->camera -> [..., 3] camera centres in world coordinates (-R^T t)."""
    rot, t = viewmat[..., :3, :3], viewmat[..., :3, 3:]
    return -(rot.transpose(-1, -2) @ t)[..., 0]


def vertex_normals(vertices: np.ndarray | Tensor, faces: np.ndarray | Tensor) -> np.ndarray:
    """Unit vertex normals [V, 3] float32 (area-weighted face normals) of vertices [V, 3], faces
    [F, 3]. Vertices of only degenerate triangles get +Z, so the result is always finite and unit."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 * area
    n = np.zeros_like(v)
    for c in range(3):
        np.add.at(n, f[:, c], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    ok = length[:, 0] > 1e-20
    out = np.tile(np.array([0.0, 0.0, 1.0]), (len(v), 1))
    out[ok] = n[ok] / length[ok]
    return out.astype(np.float32)


def knn_indices(points: Tensor, k: int) -> Tensor:
    """[N, k] indices of each of ``points [N, 3]``'s k nearest points (itself among them, first
    unless it coincides with another point); exact (a k-d tree), no gradient."""
    x = points.detach().cpu().double().numpy()
    k = min(k, len(x))
    _, idx = cKDTree(x).query(x, k=k)
    return torch.from_numpy(np.asarray(idx).reshape(len(x), k)).to(points.device)


def mean_neighbour_distance(points: Tensor, k: int, exact: bool = True) -> Tensor:
    """[N] mean distance of each of ``points [N, 3]`` (finite) to its ``k`` nearest other points
    (0.01 m when there are no others); no gradient.

    ``exact``: by a k-d tree in float64 (0.01 s for Anny's 13,718 vertices). Else by brute force,
    ``torch.cdist`` in the points' dtype (0.4 s for those vertices on two threads), whose distances
    through dot products are in float32 up to 8% off for millimetre neighbours a metre from the
    origin. The Gaussians' initial scales keep the brute force: every benchmark before b9b9fe3
    measured avatars seeded with it, and the exact distances cost the hands in far poses and new
    views (``docs/speed.md``, "Levers measured and not kept")."""
    n = points.shape[0]
    if n < 2:
        return points.new_full((n,), 0.01)
    if not torch.isfinite(points).all():
        raise ValueError("mean_neighbour_distance needs finite points")
    k = min(k, n - 1)
    if not exact:
        with torch.no_grad():
            near = [torch.cdist(p, points).topk(k + 1, dim=1, largest=False) for p in points.split(2048)]
        return torch.cat([d.values[:, 1:].mean(dim=1) for d in near])  # the first is the point itself
    xyz = points.detach().cpu().double().numpy()
    distances, _ = cKDTree(xyz).query(xyz, k=k + 1)
    return torch.from_numpy(distances[:, 1:].mean(axis=1)).to(points)


def quat_from_z(directions: Tensor) -> Tensor:
    """[N, 3] unit vectors -> [N, 4] (w, x, y, z) shortest rotations taking +z onto them."""
    z = torch.zeros_like(directions)
    z[:, 2] = 1.0
    w = 1.0 + directions[:, 2:3]
    q = torch.cat([w, torch.linalg.cross(z, directions)], dim=-1)
    # Opposite to +z: any half turn about an axis orthogonal to z.
    flip = w[:, 0] < 1e-6
    q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype)
    return q / q.norm(dim=-1, keepdim=True)
