"""``avatar.surface_frames``: Gaussians carried by the frame of the skin an expression moves."""

from __future__ import annotations

import math

import torch

from eva_engine.avatar.surface_frames import (
    LEVER_REACH,
    SCALE_RANGE,
    follow_skin,
    normals_and_areas,
    rotation_between,
)
from eva_engine.render.projection import quat_to_rotmat


def grid(n: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """A flat n x n vertex grid in z = 0 with 1 cm spacing: (vertices [n*n, 3], faces [F, 3])."""
    ys, xs = torch.meshgrid(
        torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij"
    )
    verts = torch.stack([xs.flatten(), ys.flatten(), torch.zeros(n * n, dtype=torch.float64)], -1) * 0.01
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            faces += [[a, b, e], [a, e, d]]
    return verts, torch.tensor(faces)


def gaussians_on(verts: torch.Tensor, ids: torch.Tensor, lift: float = 0.0):
    """Gaussians at ``verts[ids]`` lifted by ``lift`` along +z: means [n, 3], identity quats
    [n, 4], 1 mm scales [n, 3]."""
    n = len(ids)
    means = verts[ids] + torch.tensor([0.0, 0.0, lift], dtype=verts.dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=verts.dtype).expand(n, 4).clone()
    return means, quats, torch.full((n, 3), 1e-3, dtype=verts.dtype)


def test_rotation_between_turns_one_unit_vector_onto_another():
    g = torch.Generator().manual_seed(0)
    a = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    b = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    r = rotation_between(a, b)
    torch.testing.assert_close((r @ a.unsqueeze(-1)).squeeze(-1), b)
    torch.testing.assert_close(r @ r.transpose(-1, -2), torch.eye(3, dtype=r.dtype).expand_as(r))
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(64, dtype=r.dtype))
    torch.testing.assert_close(rotation_between(a, a), torch.eye(3, dtype=r.dtype).expand_as(r))
    assert torch.isfinite(rotation_between(a, -a)).all()  # the undefined half-turn: clamped, finite


def test_a_stretched_patch_scales_and_levers_the_gaussians_on_its_skin():
    rest, faces = grid()
    deformed = rest.clone()
    deformed[:, 1] *= 2.0  # every area doubles; the row y = 0 stays where it was
    ids = torch.tensor([12, 7, 0])  # the centre, an inner vertex, a corner that does not move
    means, quats, scales = gaussians_on(rest, ids, lift=1e-3)
    means = means + torch.tensor([2e-3, 1e-3, 0.0], dtype=rest.dtype)  # off its vertex in the plane
    out_means, out_quats, out_scales, carried, turns = follow_skin(
        means, quats, scales, ids, rest, deformed, faces
    )
    assert carried.tolist() == [0, 1]  # the corner's vertex stayed: not carried
    k = math.sqrt(2.0)
    torch.testing.assert_close(out_scales[:2], scales[:2] * k)
    torch.testing.assert_close(out_scales[2], scales[2])
    torch.testing.assert_close(out_quats, quats)  # a flat stretch does not turn the normal
    torch.testing.assert_close(turns, torch.eye(3, dtype=rest.dtype).expand(2, 3, 3))
    torch.testing.assert_close(out_means[:2], deformed[ids[:2]] + k * (means[:2] - rest[ids[:2]]))
    torch.testing.assert_close(out_means[2], means[2])
    plain = follow_skin(means, quats, scales, ids, rest, deformed, faces, frames=False)
    torch.testing.assert_close(plain[0], means + (deformed - rest)[ids])  # offsets only
    assert plain[1] is quats and plain[2] is scales and len(plain[3]) == 0


def test_a_turned_patch_turns_its_gaussians_and_levers_only_those_within_reach():
    rest, faces = grid()
    angle = math.pi / 3  # the patch folds up about the x axis, as a closing lid turns
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=rest.dtype)
    shift = torch.tensor([0.0, 0.0, 0.01], dtype=rest.dtype)
    deformed = rest @ rot.T + shift
    ids = torch.tensor([12, 12])
    means, quats, scales = gaussians_on(rest, ids)
    means = means + torch.tensor([[0.0, 0.0, 2e-3], [0.0, 0.0, 3 * LEVER_REACH]], dtype=rest.dtype)
    out_means, out_quats, out_scales, _, turns = follow_skin(means, quats, scales, ids, rest, deformed, faces)
    torch.testing.assert_close(turns, rot.expand(2, 3, 3))
    torch.testing.assert_close(quat_to_rotmat(out_quats), rot.expand(2, 3, 3))
    torch.testing.assert_close(out_scales, scales)  # a rigid turn keeps the area
    torch.testing.assert_close(out_means[0], means[0] @ rot.T + shift)  # on the skin: levered
    torch.testing.assert_close(out_means[1], means[1] + deformed[12] - rest[12])  # far off: the offset


def test_the_rest_surface_kept_for_the_whole_mesh_carries_the_same():
    """A renderer keeps the rest mesh's normals and areas (``rest_surface``); the moved vertices'
    are those computed from only the triangles around them."""
    rest, faces = grid(7)
    g = torch.Generator().manual_seed(1)
    deformed = rest.clone()
    deformed[10:20] += 2e-3 * torch.randn(10, 3, generator=g, dtype=rest.dtype)  # a patch moves
    ids = torch.arange(len(rest))
    means, quats, scales = gaussians_on(rest, ids, lift=1e-3)
    fresh = follow_skin(means, quats, scales, ids, rest, deformed, faces)
    kept = follow_skin(
        means, quats, scales, ids, rest, deformed, faces, rest_surface=normals_and_areas(rest, faces)
    )
    assert len(fresh[3]) > 0
    for a, b in zip(fresh, kept, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_collapsed_and_exploded_skin_gives_finite_bounded_gaussians_and_gradients():
    rest, faces = grid()
    ids = torch.arange(len(rest))
    means, quats, scales = gaussians_on(rest, ids, lift=1e-3)
    quats[3] = 0.0  # a zero quaternion stays zero (the rasterizer reads it as identity)
    flat = rest * torch.tensor([1.0, 0.0, 1.0], dtype=rest.dtype)
    for deformed in (flat, rest * 1e6, rest[[0]].expand_as(rest)):  # collapsed, huge, one point
        deformed = deformed.clone().requires_grad_(True)
        m, q = means.clone().requires_grad_(True), quats.clone().requires_grad_(True)
        out = follow_skin(m, q, scales, ids, rest, deformed, faces)
        for t in out[:2] + out[2:3] + out[4:]:
            assert torch.isfinite(t).all()
        ratio = out[2] / scales
        assert ratio.min() >= SCALE_RANGE[0] - 1e-9 and ratio.max() <= SCALE_RANGE[1] + 1e-9
        assert torch.equal(out[1][3], torch.zeros(4, dtype=rest.dtype))
        (out[0].sum() + out[1].sum() + out[2].sum()).backward()
        for grad in (deformed.grad, m.grad, q.grad):
            assert torch.isfinite(grad).all()


def test_an_unmoved_surface_returns_the_gaussians_untouched():
    rest, faces = grid()
    ids = torch.arange(len(rest))
    means, quats, scales = gaussians_on(rest, ids, lift=1e-3)
    out_means, out_quats, out_scales, carried, _ = follow_skin(
        means, quats, scales, ids, rest, rest.clone(), faces
    )
    assert len(carried) == 0 and out_quats is quats and out_scales is scales
    assert torch.equal(out_means, means)
