"""How a facial expression carries the Gaussians on the skin it moves.

Anny's eyelids and jaw move through blendshapes, not bones, so skinning alone leaves a Gaussian
on the upper lid where it was. Offsetting each Gaussian by its nearest vertex's displacement
(``Avatar.pose``) moves it but keeps its size and orientation: a closing lid stretches to
several times its open area and turns from facing up to facing the camera, and Gaussians sized
for the open lid, seen edge-on, leave gaps that show the eye behind it (``docs/alignment.md``,
"Eye and mouth openings").

:func:`surface_frames` gives each vertex the frame change of the surface around it: the rotation
that turns its rest normal onto its deformed normal and the square root of the change of its
surrounding area. :func:`follow_skin` turns and scales a Gaussian with its vertex's frame
(rotation ``R q``, scales ``k s``), as GaussianAvatars does with Gaussians bound to a deforming
face mesh, here per vertex since the avatar attaches Gaussians to vertices. A Gaussian on the
skin, within ``LEVER_REACH`` of its vertex, is also levered about it as GaussianAvatars' binding
does (mean ``x'_v + k R (mu - x_v)``): lips carried by a turning jaw then part as the jaw opens.
One farther off (hair over the brow, centimetres from its vertex) moves by the vertex's offset
only: levered too, it swung by millimetres whenever the skin under it turned, which cost the
seated video's face 2.5% LPIPS; levered nowhere, the mouth opened a quarter less
(``docs/alignment.md``). Vertices the expression does not move keep the identity, exactly.
"""

from __future__ import annotations

import torch
from torch import Tensor

from eva_engine.avatar.skinning import quat_multiply, rotmat_to_quat_wxyz

SCALE_RANGE = (0.25, 4.0)  # a vertex's area may shrink or grow 16x, no more: degenerate triangles
LEVER_REACH = 0.01  # metres: skin-borne Gaussians; hair and the like sit farther from their vertex
MOVED = 1e-7  # metres: a vertex displaced less keeps the identity frame (float noise, not skin)
_EPS = 1e-12


def normals_and_areas(vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """(unit vertex normals [V, 3] (area-weighted; +Z where undefined), vertex areas [V] (a
    third of each incident triangle's)) of ``vertices [V, 3]`` with ``faces [F, 3]``."""
    v0, v1, v2 = (vertices[faces[:, c]] for c in range(3))
    cross = torch.linalg.cross(v1 - v0, v2 - v0)  # [F, 3], length = 2 * area
    normals = torch.zeros_like(vertices)
    areas = vertices.new_zeros(vertices.shape[0])
    tri_area = cross.norm(dim=-1) / 6.0  # a third of each triangle's area per corner
    for c in range(3):
        normals = normals.index_add(0, faces[:, c], cross)
        areas = areas.index_add(0, faces[:, c], tri_area)
    length = normals.norm(dim=-1, keepdim=True)
    up = torch.zeros_like(normals)
    up[:, 2] = 1.0
    normals = torch.where(length > _EPS, normals / length.clamp_min(_EPS), up)
    return normals, areas


def rotation_between(a: Tensor, b: Tensor) -> Tensor:
    """[..., 3, 3] the smallest rotation taking unit vectors ``a [..., 3]`` onto ``b [..., 3]``
    (Rodrigues; a turn near 180 degrees, whose axis is undefined, is clamped, not NaN)."""
    v = torch.linalg.cross(a, b)
    c = (a * b).sum(dim=-1)
    zero = torch.zeros_like(c)
    vx = torch.stack(
        [
            torch.stack([zero, -v[..., 2], v[..., 1]], dim=-1),
            torch.stack([v[..., 2], zero, -v[..., 0]], dim=-1),
            torch.stack([-v[..., 1], v[..., 0], zero], dim=-1),
        ],
        dim=-2,
    )
    eye = torch.eye(3, dtype=a.dtype, device=a.device).expand_as(vx)
    return eye + vx + (vx @ vx) / (1.0 + c).clamp_min(1e-6)[..., None, None]


def surface_frames(
    rest: Tensor,
    deformed: Tensor,
    faces: Tensor,
    moved: Tensor,
    rest_surface: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """Per-vertex frame change of a mesh from ``rest [V, 3]`` to ``deformed [V, 3]``.

    faces: [F, 3]; moved: [V] bool, the vertices to compute (the others get the identity);
    rest_surface: ``normals_and_areas(rest, faces)`` when the caller keeps it (the same rest for
    every frame). Returns (rotations [M, 3, 3], scales [M]) for the M moved vertices, in the
    order of ``moved.nonzero()``: the turn of the vertex normal and sqrt(deformed area / rest
    area), clamped to ``SCALE_RANGE``.
    """
    # A vertex's normal and area come from the triangles around it: only those of moved vertices.
    around = faces[moved[faces].any(dim=-1)]
    n0, a0 = rest_surface if rest_surface is not None else normals_and_areas(rest, around)
    n1, a1 = normals_and_areas(deformed, around)
    n0, a0, n1, a1 = n0[moved], a0[moved], n1[moved], a1[moved]
    scale = (a1.clamp_min(_EPS) / a0.clamp_min(_EPS)).sqrt().clamp(*SCALE_RANGE)
    return rotation_between(n0, n1), scale


def follow_skin(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    vertex_ids: Tensor,
    rest: Tensor,
    deformed: Tensor,
    faces: Tensor,
    frames: bool = True,
    reach: float = LEVER_REACH,
    rest_surface: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Canonical Gaussians carried from the ``rest [V, 3]`` surface to the ``deformed [V, 3]`` one
    (module docstring): each moves by its vertex's offset; with ``frames``, one whose vertex moved
    also turns and scales with the vertex's frame, and if it lies within ``reach`` metres of its
    vertex its offset from the vertex turns and scales too.

    means: [N, 3]; quats: [N, 4] (w, x, y, z); scales: [N, 3]; vertex_ids: [N] each Gaussian's
    vertex; faces: [F, 3]; rest_surface: ``normals_and_areas(rest, faces)``, kept by a caller
    that carries Gaussians from one rest for many frames. Returns (means [N, 3], quats [N, 4],
    scales [N, 3], carried [M] the indices of the Gaussians whose vertex moved, rotations
    [M, 3, 3] theirs; M = 0 without ``frames``). Without ``frames`` or with no vertex moved,
    quats and scales are returned as they are.
    """
    means = means + (deformed - rest)[vertex_ids]
    moved = (deformed - rest).abs().amax(dim=-1) > MOVED
    if not frames or not bool(moved[vertex_ids].any()):
        return means, quats, scales, vertex_ids.new_zeros(0), quats.new_zeros(0, 3, 3)
    rot_v, scale_v = surface_frames(rest, deformed, faces, moved, rest_surface)
    slot = torch.full_like(moved, -1, dtype=torch.long)
    slot[moved] = torch.arange(int(moved.sum()), device=moved.device)
    carried = torch.nonzero(moved[vertex_ids]).squeeze(-1)  # [M] Gaussians
    vid = vertex_ids[carried]
    rot, k = rot_v[slot[vid]], scale_v[slot[vid]]  # [M, 3, 3], [M]
    local = means[carried] - deformed[vid]  # = the canonical offset from the rest vertex
    near = (local.norm(dim=-1, keepdim=True) < reach).to(local)
    lever = k[:, None] * (rot @ local.unsqueeze(-1)).squeeze(-1) - local
    out_means = means.index_add(0, carried, near * lever)
    out_quats = quats.index_copy(0, carried, quat_multiply(rotmat_to_quat_wxyz(rot), quats[carried]))
    out_scales = scales.index_copy(0, carried, scales[carried] * k[:, None])
    return out_means, out_quats, out_scales, carried, rot
