"""The avatar model: identity at initialisation, exact LBS of Gaussians on vertices, finite
gradients for extreme poses and degenerate Gaussians."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from helpers.scenes import front_camera, random_params

from eva_engine.avatar import (
    Avatar,
    AvatarConfig,
    Camera,
    blend_skinning_weights,
    orthonormalize,
    positional_encoding,
    quat_multiply,
    skin_gaussians,
)
from eva_engine.avatar.networks import make_mlp, relu_mlp
from eva_engine.avatar.skinning import blend_transforms, sparse_weights
from eva_engine.memo import InferenceMemo

SMALL = dict(init_max_gaussians=600, mlp_width=16, pe_frequencies=2, sh_degree=1)


@pytest.fixture(scope="module")
def avatars(anny_model):
    torch.manual_seed(0)
    full = Avatar.create(anny_model, anny_model.shape_defaults, AvatarConfig(**SMALL), seed=3)
    plain = Avatar.create(
        anny_model,
        anny_model.shape_defaults,
        AvatarConfig(**SMALL, weight_offsets=False, pose_refine=False),
        seed=3,
    )
    return full, plain


def test_mlps_start_as_identity(anny_model, avatars):
    full, plain = avatars
    assert torch.equal(full.gaussians.means, plain.gaussians.means)
    params = random_params(anny_model, 1, seed=1)
    # Pose refinement: the input pose to ~1e-5 rad; weights: the body model's.
    refined = full.refine_pose(params)
    torch.testing.assert_close(refined.joints, params.joints, atol=1e-4, rtol=0)
    base = anny_model.skinning_weights[full.gaussians.vertex_ids]
    torch.testing.assert_close(full.skinning_weights(), base, atol=1e-4, rtol=0)
    # First render equals plain LBS.
    cam = front_camera(48)
    a = full(params, cam, torch.ones(3)).image
    b = plain(params, cam, torch.ones(3)).image
    torch.testing.assert_close(a, b, atol=2e-3, rtol=0)
    # The MLPs are not dead: their last layers are small but non-zero, so gradients reach them.
    loss = full(params, cam, torch.ones(3)).image.mean()
    loss.backward()
    grads = [p.grad for p in full.mlp_parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)
    full.zero_grad()


def test_skinning_weights_are_reused_only_while_nothing_they_depend_on_changes(anny_model):
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, AvatarConfig(**SMALL), seed=3)
    with torch.no_grad():
        first = avatar.skinning_weights()
        assert avatar.skinning_weights() is first  # rendering: computed once
        next(avatar.weight_offsets.parameters()).mul_(1.5)  # an in-place update (an optimizer step)
        changed = avatar.skinning_weights()
        assert changed is not first and not torch.equal(changed, first)
        avatar.gaussians.means.add_(0.01)
        assert avatar.skinning_weights() is not changed
    with_grad = avatar.skinning_weights()  # training: never cached, differentiable
    assert with_grad.requires_grad and avatar.skinning_weights() is not with_grad


def test_a_render_poses_the_gaussians_as_training_does(anny_model, avatars):
    """Without autograd the Gaussians are blended with sparse weights and the shape's kept rest
    (``Avatar.pose``): the same posed Gaussians as the dense, differentiable path."""
    avatar, _ = avatars  # with the weight and pose MLPs
    for seed in (4, 5):
        params = random_params(anny_model, 1, seed=seed)
        params.expression[:, :8] = 0.6
        with torch.no_grad():
            rendered = avatar.pose(params)
        trained = avatar.pose(params)
        assert trained.means.requires_grad
        torch.testing.assert_close(rendered.means, trained.means.detach(), atol=1e-5, rtol=0)
        torch.testing.assert_close(rendered.quats, trained.quats.detach(), atol=1e-5, rtol=0)
        torch.testing.assert_close(rendered.sh, trained.sh.detach(), atol=0, rtol=0)
    with torch.no_grad():  # a rendered avatar copies (its kept values do not travel)
        copied = copy.deepcopy(avatar)
        torch.testing.assert_close(copied.pose(params).means, avatar.pose(params).means)


def test_gaussians_on_vertices_follow_the_body_exactly(anny_model, avatars):
    _, plain = avatars
    params = random_params(anny_model, 1, seed=2)
    params.expression[:, :5] = 0.7  # expression moves the rest vertices (blendshapes)
    posed = plain.pose(params)
    verts = anny_model(plain.subject_params(params)).vertices[0]
    torch.testing.assert_close(posed.means, verts[plain.gaussians.vertex_ids], atol=1e-5, rtol=0)
    # At the rest pose with no expression the posed Gaussians are the canonical ones.
    rest = plain.pose(anny_model.default_params(1))
    torch.testing.assert_close(rest.means, plain.gaussians.means, atol=1e-6, rtol=0)
    q = plain.gaussians.splats["quats"]
    torch.testing.assert_close(rest.quats, q, atol=1e-6, rtol=0)


def test_skinning_rotates_quaternions_with_a_rigid_transform():
    torch.manual_seed(0)
    angle = 0.7
    rot = torch.tensor(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    )
    t = torch.eye(4)
    t[:3, :3], t[:3, 3] = rot, torch.tensor([0.1, 0.2, 0.3])
    transforms = torch.stack([t, t])
    means = torch.randn(5, 3)
    quats = torch.nn.functional.normalize(torch.randn(5, 4), dim=-1)
    weights = torch.softmax(torch.randn(5, 2), dim=-1)
    posed, pq, r = skin_gaussians(means, quats, weights, transforms)
    torch.testing.assert_close(posed, means @ rot.T + t[:3, 3])
    torch.testing.assert_close(r, rot.expand(5, 3, 3))
    from eva_engine.render import quat_to_rotmat

    torch.testing.assert_close(quat_to_rotmat(pq), rot @ quat_to_rotmat(quats), atol=1e-5, rtol=0)
    # Hamilton product conventions: i * j = k.
    i, j = torch.tensor([0.0, 1, 0, 0]), torch.tensor([0.0, 0, 1, 0])
    torch.testing.assert_close(quat_multiply(i, j), torch.tensor([0.0, 0, 0, 1]))


def test_relu_mlp_matches_autograd_through_the_layers():
    gen = torch.Generator().manual_seed(0)
    mlp = make_mlp(9, 5, 16, 2, 1.0, gen).double()
    x = torch.randn(40, 9, generator=gen, dtype=torch.float64)
    x[:5] = 0.0  # rows whose hidden units sit at the ReLU's kink
    x.requires_grad_(True)
    grad = torch.randn(40, 5, generator=gen, dtype=torch.float64)
    table = torch.log(torch.rand(7, 5, generator=gen, dtype=torch.float64) + 1e-8)
    rows = torch.randint(0, 7, (40,), generator=gen)
    wrt = [x, *mlp.parameters()]
    # Plain, and with a log prior and a softmax (the skinning weights softmax(log(w + eps) + f_w)).
    for log_prior, reference in (
        (None, mlp(x)),
        ((table, rows), torch.softmax(mlp(x) + table[rows], dim=-1)),
    ):
        expected = torch.autograd.grad(reference, wrt, grad)
        out = relu_mlp(x, mlp, chunk=16, log_prior=log_prior)  # three chunks, the last one short
        torch.testing.assert_close(out, reference, atol=1e-12, rtol=0)
        for a, b in zip(torch.autograd.grad(out, wrt, grad), expected, strict=True):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)
    # An input that needs no gradient gets none; the parameters still do.
    out = relu_mlp(x.detach(), mlp, chunk=16)
    assert all(g is not None for g in torch.autograd.grad(out.sum(), list(mlp.parameters())))


def test_relu_mlp_in_bfloat16_stays_close_and_float32():
    """The bfloat16 products (``relu_mlp(bf16=True)``): float32 outputs and gradients, near the
    float32 ones (the layers' gradients differ by ~5% here: bfloat16 keeps 8 bits of mantissa, and
    units at the ReLU's kink can switch); the softmax's rows still sum to one."""
    gen = torch.Generator().manual_seed(0)
    mlp = make_mlp(39, 104, 128, 2, 0.5, gen)
    x = torch.randn(300, 39, generator=gen, requires_grad=True)
    table = torch.log_softmax(torch.randn(50, 104, generator=gen), dim=-1)
    rows = torch.randint(0, 50, (300,), generator=gen)
    grad = torch.randn(300, 104, generator=gen)
    wrt = [x, *mlp.parameters()]
    outs = [relu_mlp(x, mlp, chunk=128, log_prior=(table, rows), bf16=b) for b in (False, True)]
    grads = [torch.autograd.grad(out, wrt, grad) for out in outs]
    assert outs[1].dtype == torch.float32 and all(g.dtype == torch.float32 for g in grads[1])
    torch.testing.assert_close(outs[1].sum(-1), torch.ones(300), atol=1e-5, rtol=0)
    torch.testing.assert_close(outs[1], outs[0], atol=2e-3, rtol=0.05)
    for a, b in zip(grads[1], grads[0], strict=True):
        assert torch.isfinite(a).all() and float((a - b).norm() / b.norm()) < 0.1


def test_blend_weights_and_encoding():
    base = torch.tensor([[1.0, 0.0, 0.0], [0.25, 0.75, 0.0]])
    torch.testing.assert_close(blend_skinning_weights(base, None), base, atol=1e-7, rtol=0)
    w = blend_skinning_weights(base, torch.tensor([[0.0, 0.0, 0.0], [math.log(3.0), 0.0, 0.0]]))
    torch.testing.assert_close(w[1, :2], torch.tensor([0.5, 0.5]), atol=1e-6, rtol=0)
    enc = positional_encoding(torch.zeros(4, 3), 3)
    assert enc.shape == (4, 21) and torch.equal(enc[:, :3], torch.zeros(4, 3))


def test_sparse_weights_blend_as_the_dense_ones():
    gen = torch.Generator().manual_seed(0)
    logits = torch.full((50, 104), -18.4)  # the softmax's ~1e-8 floor on the bones not followed
    logits.scatter_(1, torch.randint(0, 104, (50, 3), generator=gen), torch.randn(50, 3, generator=gen))
    logits[0] = 0.0  # a row spread evenly over every bone: each under 1e-2, all kept
    weights = torch.softmax(logits, dim=1)
    transforms = torch.eye(4).repeat(104, 1, 1)
    transforms[:, :3, 3] = torch.randn(104, 3, generator=gen)
    sparse = sparse_weights(weights)
    assert sparse.layout == torch.sparse_csr and sparse._nnz() <= 50 * 3 + 104
    torch.testing.assert_close(
        blend_transforms(sparse, transforms), blend_transforms(weights, transforms), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(sparse.to_dense().sum(1), torch.ones(50))
    tiny = sparse_weights(torch.tensor([[0.5e-6, 1e-7, 0.0]]))  # nothing over the floor
    torch.testing.assert_close(tiny.to_dense(), torch.tensor([[1.0, 0.0, 0.0]]))


def test_the_inference_memo_keeps_a_value_only_while_its_inputs_are_unchanged():
    calls = []
    a, b = torch.ones(3), torch.zeros(2)

    def compute():
        calls.append(1)
        return a.sum() + b.sum()

    memo = InferenceMemo()
    with torch.no_grad():
        first = memo.get([a, b], compute)
        assert memo.get([a, b], compute) is first and len(calls) == 1
        a.add_(1.0)  # in place: a new version
        assert float(memo.get([a, b], compute)) == 6.0 and len(calls) == 2
        b = torch.zeros(2)  # another tensor, equal values
        memo.get([a, b], compute)
        assert len(calls) == 3
    memo.get([a, b], compute)  # autograd on: computed every time, never kept
    memo.get([a, b], compute)
    assert len(calls) == 5
    with torch.no_grad():
        memo.get([a, b], compute)
    assert len(calls) == 6


def test_the_inference_memo_compares_its_key_by_value():
    calls = []
    memo = InferenceMemo()
    with torch.no_grad():
        first = memo.get([], lambda: calls.append(1) or torch.ones(1), key=[torch.tensor([1.0, 2.0])])
        again = memo.get(
            [], lambda: calls.append(1), key=[torch.tensor([1.0, 2.0])]
        )  # new tensor, same values
        assert again is first and len(calls) == 1
        for other in ([torch.tensor([1.0, 2.5])], [torch.tensor([1.0, 2.0], dtype=torch.float64)], []):
            memo.get([], lambda: calls.append(1), key=other)
        assert len(calls) == 4
        nan = [torch.tensor([float("nan")])]
        memo.get([], lambda: calls.append(1), key=nan)
        memo.get([], lambda: calls.append(1), key=nan)  # NaN equals nothing: computed again
        assert len(calls) == 6


def test_a_render_that_changes_only_the_camera_reuses_the_posed_gaussians(anny_model):
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, AvatarConfig(**SMALL), seed=4)
    params = random_params(anny_model, 1, seed=5)
    params.expression[0, 0] = 0.6  # with an expression: the skin's frames too
    with torch.no_grad():
        posed = avatar.pose(params)
        assert avatar.pose(params.map(torch.clone)) is posed  # equal values, new tensors
        moved = params.map(torch.clone)
        moved.joints[0, 3, 0] += 0.1
        assert avatar.pose(moved) is not posed
        avatar.gaussians.splats["means"].add_(0.01)  # the avatar changed in place: posed again
        fresh = avatar.pose(params)
        shift = (fresh.means - posed.means).norm(dim=-1)  # 1.7 cm in canonical space
        assert fresh is not posed and bool(((shift > 0.01) & (shift < 0.03)).all())
        # The kept pose renders what posing anew renders, through another camera too.
        for cam in (front_camera(24), _behind_camera(24)):
            kept = avatar.render(params, cam)
            avatar._posed_memo = InferenceMemo()
            torch.testing.assert_close(kept, avatar.render(params, cam), atol=0, rtol=0)
    with_grad = avatar.pose(params)  # training: never kept
    assert with_grad is not avatar.pose(params) and with_grad.means.requires_grad


def test_degenerate_blends_stay_finite():
    m = torch.zeros(3, 3, 3, requires_grad=True)  # all-zero blended matrix (opposite rotations)
    r = orthonormalize(m)
    r.sum().backward()
    assert torch.isfinite(r).all() and torch.isfinite(m.grad).all()


def test_extreme_poses_and_degenerate_gaussians_have_finite_gradients(anny_model):
    torch.manual_seed(0)
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, AvatarConfig(**SMALL), seed=1)
    g = avatar.gaussians
    with torch.no_grad():
        g.splats["quats"][:10] = 0.0  # zero quaternions
        g.splats["scales"][10:20] = -30.0  # tiny
        g.splats["scales"][20:30] = 3.0  # huge
        g.splats["opacities"][30:40] = 40.0  # saturated
        g.splats["opacities"][40:50] = -40.0
    params = anny_model.default_params(1)
    gen = torch.Generator().manual_seed(0)
    params.joints = (
        torch.rand(params.joints.shape, generator=gen) * 2 - 1
    ) * math.pi  # any rotation, up to pi
    params.root_orient = torch.tensor([[0.0, math.pi, 0.0]])
    params.expression[:] = 1.0
    for cam in (front_camera(32), _behind_camera(32)):
        out = avatar(params, cam, torch.ones(3))
        loss = out.image.mean() + out.alpha.mean() + out.depth.mean()
        loss.backward()
        assert torch.isfinite(out.image).all()
        for name, p in [*g.splats.items(), *avatar.named_parameters()]:
            if p.grad is not None:
                assert torch.isfinite(p.grad).all(), name
        avatar.zero_grad()


def _behind_camera(size: int) -> Camera:
    """A camera inside the body looking along -Z: many Gaussians behind it or at its centre."""
    cam = front_camera(size)
    cam.viewmat = cam.viewmat.clone()
    cam.viewmat[2, 3] = 0.0
    return cam


def test_render_api(anny_model, avatars):
    full, _ = avatars
    image = full.render(
        anny_model.params_from_pose({"joints": {"lowerarm01.L": [0, 0, -1.0]}}), front_camera(40)
    )
    assert image.shape == (40, 40, 3) and image.min() >= 0 and image.max() <= 1
    assert not image.requires_grad
    with pytest.raises(ValueError, match="one frame"):
        full.pose(anny_model.default_params(2))
