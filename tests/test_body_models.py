"""The BodyModel contract, checked on both backends (Anny and a generated SMPL-X file)."""

import math

import pytest
import torch
import trimesh

from eva_engine.body import (
    KEYPOINT_NAMES,
    PART_NAMES,
    BodyModel,
    BodyParams,
    lbs,
    nearest_vertex_index,
    nearest_vertex_weights,
)

BACKENDS = ["anny", "smplx"]


@pytest.fixture(params=BACKENDS)
def model(request, body_models) -> BodyModel:
    return body_models[request.param]


def random_params(model: BodyModel, batch: int, scale: float = 0.4, seed: int = 0) -> BodyParams:
    g = torch.Generator().manual_seed(seed)
    p = model.default_params(batch)
    p.joints.copy_(torch.randn(p.joints.shape, generator=g) * scale)
    p.root_orient.copy_(torch.randn(p.root_orient.shape, generator=g))
    p.transl.copy_(torch.randn(p.transl.shape, generator=g))
    if model.name == "anny":  # phenotypes and ARKit coefficients live in [0, 1]
        p.shape.copy_(torch.rand(p.shape.shape, generator=g))
        p.expression.copy_(torch.rand(p.expression.shape, generator=g))
    else:
        p.shape.copy_(torch.randn(p.shape.shape, generator=g))
        p.expression.copy_(torch.randn(p.expression.shape, generator=g))
    return p


def test_interface_facts(model):
    v, j = model.num_vertices, model.num_joints
    assert model.faces.dtype == torch.int64 and model.faces.shape[1] == 3
    assert int(model.faces.min()) >= 0 and int(model.faces.max()) < v
    assert model.parents.shape == (j,) and int(model.parents[0]) == -1
    assert all(0 <= int(model.parents[i]) < j for i in range(1, j))
    assert model.skinning_weights.shape == (v, j)
    assert torch.allclose(model.skinning_weights.sum(1), torch.ones(v), atol=1e-5)
    assert (model.skinning_weights >= 0).all()
    assert model.part_ids.shape == (v,) and int(model.part_ids.max()) < len(PART_NAMES)
    assert model.surface_vertex_mask.shape == (v,) and model.surface_vertex_mask.dtype == torch.bool
    assert len(model.joint_names) == j and len(set(model.joint_names)) == j
    assert model.pose_joint_names == model.joint_names[1:]
    assert model.keypoint_names == list(KEYPOINT_NAMES) and len(KEYPOINT_NAMES) == 91
    assert model.shape_defaults.shape == (len(model.shape_names),)
    assert model.dtype == torch.float32


def test_zero_params_give_the_rest_pose(model):
    params = model.default_params(2)
    out = model(params)
    eye = torch.eye(4).expand_as(out.transforms)
    assert torch.allclose(out.transforms, eye, atol=1e-6)
    assert torch.allclose(out.vertices, model.canonical(params), atol=1e-6)
    assert out.vertices.shape == (2, model.num_vertices, 3)
    assert out.joints.shape == (2, model.num_joints, 3)


def test_lbs_with_transforms_reproduces_posed_vertices(model):
    params = random_params(model, batch=3)
    out = model(params)
    skinned = lbs(model.canonical(params), model.skinning_weights, out.transforms)
    assert (skinned - out.vertices).abs().max() <= 1e-5
    assert torch.equal(out.rest, model.canonical(params))  # the rest it carries is canonical's
    # Transforms are rigid: rotation part orthonormal, last row [0, 0, 0, 1].
    rot = out.transforms[..., :3, :3]
    assert torch.allclose(rot @ rot.transpose(-1, -2), torch.eye(3).expand_as(rot), atol=1e-5)
    assert torch.equal(
        out.transforms[..., 3, :], torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(3, model.num_joints, 4)
    )
    # Joints are the rest joint heads carried by their own transforms.
    assert out.joints.isfinite().all()


def test_root_orient_and_transl_semantics(model):
    params = model.default_params(1)
    rest = model(params)
    params.root_orient[0] = torch.tensor([0.0, math.pi / 2, 0.0])
    params.transl[0] = torch.tensor([1.0, 2.0, 3.0])
    out = model(params)
    root = rest.joints[0, 0]
    # The root joint stays in place up to the translation; a point in front of it (+Z) turns
    # to +X under +90 deg about Y.
    assert torch.allclose(out.joints[0, 0], root + params.transl[0], atol=1e-5)
    rel_rest = rest.vertices[0] - root
    rel = out.vertices[0] - root - params.transl[0]
    expected = torch.stack([rel_rest[:, 2], rel_rest[:, 1], -rel_rest[:, 0]], dim=1)
    assert torch.allclose(rel, expected, atol=1e-5)


def extreme_params(model: BodyModel) -> BodyParams:
    """Fingers fully curled, arms behind the back, 180 deg root turns, extreme shapes."""
    names = model.pose_joint_names
    batch = 6
    p = model.default_params(batch)
    fingers = [
        i
        for i, n in enumerate(names)
        if "finger" in n or any(f in n for f in ("index", "middle", "pinky", "ring", "thumb"))
    ]
    assert len(fingers) >= 28
    upper_arms = [
        i
        for i, n in enumerate(names)
        if n in ("upperarm01.L", "upperarm01.R", "left_shoulder", "right_shoulder")
    ]
    elbows = [
        i for i, n in enumerate(names) if n in ("lowerarm01.L", "lowerarm01.R", "left_elbow", "right_elbow")
    ]
    assert len(upper_arms) == 2 and len(elbows) == 2
    p.joints[0, fingers] = torch.tensor([0.0, 0.0, 1.6])  # curled: ~90 deg at every finger joint
    p.joints[1, fingers] = torch.tensor([1.6, 0.0, 0.0])
    p.joints[2, upper_arms] = torch.tensor([2.6, 0.0, 0.0])  # arms swung behind the back
    p.joints[2, elbows] = torch.tensor([0.0, 2.8, 0.0])
    p.root_orient[3] = torch.tensor([0.0, math.pi, 0.0])  # 180 deg turns, exactly pi
    p.root_orient[4] = torch.tensor([math.pi, 0.0, 0.0])
    p.joints[5] = 3.0  # everything twisted hard
    if model.name == "anny":
        p.shape[0] = 0.0
        p.shape[1] = 1.0
        p.shape[2] = torch.tensor([1.0, 0.0, 1.0, 0.0, 1.0, 0.0])
        p.shape[3] = -0.5  # out of range: Anny clamps
        p.shape[4] = 1.5
        p.expression[:3] = 1.0
    else:
        p.shape[:3] = torch.tensor([5.0, -5.0, 3.0])[:, None]
        p.expression[:3] = 4.0
    return p


def test_extreme_poses_and_shapes_finite_values_and_gradients(model):
    params = extreme_params(model).map(lambda t: t.detach().requires_grad_(True))
    out = model(params)
    assert out.vertices.isfinite().all() and out.joints.isfinite().all() and out.transforms.isfinite().all()
    kp = model.keypoints(out)
    assert kp.isfinite().all()
    loss = out.vertices.square().mean() + kp.square().mean() + out.transforms.square().mean()
    loss.backward()
    for name, tensor in params.tensors().items():
        assert tensor.grad is not None, name
        assert tensor.grad.isfinite().all(), name


def test_gradients_finite_at_exactly_zero_rotation(model):
    params = model.default_params(1, requires_grad=True)
    out = model(params)
    (out.vertices.sin().sum() + model.keypoints(out).sum()).backward()
    for name, tensor in params.tensors().items():
        assert tensor.grad.isfinite().all(), name
    assert params.joints.grad.abs().sum() > 0  # rotations are not dead at zero


def test_part_ids_plausible_and_hand_vertices_near_hand_joints(model):
    counts = torch.bincount(model.part_ids, minlength=3)
    v = model.num_vertices
    hand, face = int(counts[PART_NAMES.index("hand")]), int(counts[PART_NAMES.index("face")])
    assert 0.05 * v < hand < 0.4 * v
    assert 0.05 * v < face < 0.6 * v
    params = model.default_params(1)
    out = model(params)
    verts = out.vertices[0][model.part_vertex_ids("hand")]
    hand_joint = [
        i
        for i, n in enumerate(model.joint_names)
        if "wrist" in n
        or "finger" in n
        or "metacarpal" in n
        or n[:-1].endswith(("index", "middle", "pinky", "ring", "thumb"))
    ]
    dist = torch.cdist(verts, out.joints[0, hand_joint]).min(dim=1).values
    assert dist.max() < 0.08, f"a hand vertex is {dist.max():.3f} m from every hand joint"


ARM = {  # shoulder, elbow, middle knuckle per backend
    "anny": ("upperarm01.L", "lowerarm01.L", "finger3-1.L"),
    "smplx": ("left_shoulder", "left_elbow", "left_middle1"),
}


def _skin_path(model, canonical, transforms, a, b, n, k):
    path = a + torch.linspace(0.0, 1.0, n)[:, None] * (b - a)
    w = nearest_vertex_weights(path, canonical, model.skinning_weights, k=k)
    posed = lbs(path, w, transforms)[0]
    return (posed[1:] - posed[:-1]).norm(dim=1)


def test_nearest_vertex_skinning_is_continuous(model):
    """Points skinned with weights borrowed from their nearest vertices move continuously: along
    a straight path from the shoulder to the knuckles through a bent elbow, the largest step of
    the posed path shrinks with the sampling step (k=1, EVA's rule, jumps instead)."""
    shoulder, elbow, knuckle = (model.joint_names.index(n) for n in ARM[model.name])
    params = model.default_params(1)
    params.joints[0, elbow - 1] = torch.tensor([0.0, -1.5, 0.0])
    params.joints[0, shoulder - 1] = torch.tensor([0.0, 0.0, -0.8])
    rest_joints = model(model.default_params(1)).joints[0]
    canonical = model.canonical(params)[0]
    out = model(params)
    a, b = rest_joints[shoulder], rest_joints[knuckle]
    coarse = _skin_path(model, canonical, out.transforms, a, b, 4001, k=4).max()
    fine = _skin_path(model, canonical, out.transforms, a, b, 16001, k=4).max()
    assert coarse < 5e-3
    assert fine < 0.5 * coarse, (float(coarse), float(fine))
    # Weights of a point on a vertex are that vertex's weights, for both rules.
    for k in (1, 4):
        w_v = nearest_vertex_weights(canonical[:50], canonical, model.skinning_weights, k=k)
        assert torch.allclose(w_v, model.skinning_weights[:50], atol=1e-5)
        assert torch.allclose(w_v.sum(1), torch.ones(50), atol=1e-5)


def test_keypoints_layout(model):
    params = random_params(model, batch=2)
    out = model(params)
    kp = model.keypoints(out)
    assert kp.shape == (2, 91, 3)
    # Rigid invariance: translating the body translates every keypoint.
    params.transl += torch.tensor([0.5, -1.0, 2.0])
    kp2 = model.keypoints(model(params))
    assert torch.allclose(kp2 - kp, torch.tensor([0.5, -1.0, 2.0]).expand_as(kp), atol=1e-5)


def test_posed_keypoints_equal_keypoints_of_the_posed_mesh(model):
    params = random_params(model, batch=3, seed=5)
    kp, joints = model.posed_keypoints(params)
    out = model(params)
    assert torch.allclose(kp, model.keypoints(out), atol=5e-5)
    assert torch.allclose(joints, out.joints, atol=1e-6)
    # Gradients reach every parameter through the fast path too.
    params = params.map(lambda t: t.clone().requires_grad_(True))
    model.posed_keypoints(params)[0].square().sum().backward()
    for name, t in params.tensors().items():
        assert t.grad is not None and torch.isfinite(t.grad).all(), name
        if name != "expression" or model.name == "anny":
            assert t.grad.abs().sum() > 0, name


def test_shape_shared_by_expanding_one_row(model):
    params = random_params(model, batch=4, seed=6)
    shared = params.shape[:1].expand(4, -1)
    expanded = BodyParams(params.root_orient, params.transl, params.joints, params.expression, shared)
    copied = BodyParams(params.root_orient, params.transl, params.joints, params.expression, shared.clone())
    assert torch.allclose(model(expanded).vertices, model(copied).vertices, atol=1e-6)
    assert torch.allclose(model.posed_keypoints(expanded)[0], model.posed_keypoints(copied)[0], atol=1e-5)


def test_rest_and_transforms_are_forwards_without_autograd_too(model):
    """The render path's ``rest_and_transforms`` equals ``forward``'s rest and transforms, with
    autograd and without (Anny then keeps the last shape's rest and adds the expression's), also
    after the shape or the expression changes."""
    for seed in (7, 8, 8):  # the repeat: the shape's kept rest is used
        params = random_params(model, batch=1, seed=seed)
        out = model(params)
        with torch.no_grad():
            rest, transforms = model.rest_and_transforms(params)
            params.expression.zero_()
            neutral_rest, _ = model.rest_and_transforms(params)
        torch.testing.assert_close(rest, out.rest, atol=2e-6, rtol=0)
        torch.testing.assert_close(transforms, out.transforms, atol=2e-6, rtol=0)
        torch.testing.assert_close(neutral_rest, model(params).rest, atol=2e-6, rtol=0)
        torch.testing.assert_close(neutral_rest, model.canonical(params), atol=2e-6, rtol=0)


def test_nearest_vertices_are_the_brute_force_ones(model):
    """The k-d tree search (CPU) returns the same nearest vertices and distances as comparing
    every point with every vertex in float64, and copes with no points at all."""
    from eva_engine.body.model import _knn

    vertices = model.canonical(model.default_params(1))[0]
    g = torch.Generator().manual_seed(3)
    points = vertices[torch.randint(0, len(vertices), (3000,), generator=g)]
    points = points + 0.02 * torch.randn(points.shape, generator=g)
    points[:10] = vertices[:10]  # on a vertex: distance 0
    brute = torch.cdist(points.double(), vertices.double())
    dist, idx = _knn(points, vertices, 4)
    expected = brute.topk(4, dim=1, largest=False)
    torch.testing.assert_close(dist.double(), expected.values, atol=1e-6, rtol=0)
    assert (idx == expected.indices).float().mean() > 0.999  # only float32 near-ties may swap
    assert torch.equal(nearest_vertex_index(points, vertices), brute.argmin(dim=1))
    assert nearest_vertex_index(points[:0], vertices).shape == (0,)
    assert nearest_vertex_weights(points[:0], vertices, model.skinning_weights).shape == (0, model.num_joints)


def test_keypoints_sides_and_order_at_rest(model):
    kp = model.keypoints(model(model.default_params(1)))[0]
    k = {n: kp[i] for i, n in enumerate(KEYPOINT_NAMES)}
    sided = ["shoulder", "elbow", "wrist", "hip", "knee", "ankle", "hand_thumb_ip", "hand_pinky_dip"]
    if model.name == "anny":  # the generated SMPL-X file's landmark vertices are arbitrary
        sided += ["eye_outer", "eye_inner", "ear", "eye", "hand_thumb_tip", "hand_pinky_tip"]
    for name in sided:
        assert k[f"left_{name}"][0] > k[f"right_{name}"][0], name  # subject's left is +X
    assert k["nose"][1] > k["left_shoulder"][1] > k["left_hip"][1] > k["left_knee"][1] > k["left_ankle"][1]
    if model.name == "anny":  # the stick-figure SMPL-X file has no face to face forward with
        assert k["nose"][2] > k["left_ear"][2]  # faces +Z
        assert k["left_foot_index"][2] > k["left_heel"][2]
        for side in ("left", "right"):
            h = f"{side}_hand_"
            wrist = k[h + "wrist"]
            for finger in ("index_finger", "middle_finger", "ring_finger", "pinky"):
                d = [float((k[h + f"{finger}_{j}"] - wrist).norm()) for j in ("mcp", "pip", "dip", "tip")]
                assert d == sorted(d), (side, finger, d)


@pytest.mark.parametrize("suffix", [".ply", ".glb"])
def test_posed_mesh_exports_and_reloads(model, tmp_path, suffix):
    out = model(random_params(model, batch=1))
    mesh = trimesh.Trimesh(
        vertices=out.vertices[0].detach().numpy(), faces=model.faces.numpy(), process=False
    )
    path = tmp_path / f"posed{suffix}"
    mesh.export(path)
    loaded = trimesh.load(path, force="mesh", process=False)
    assert len(loaded.vertices) == model.num_vertices
    assert len(loaded.faces) == len(model.faces)


def test_batch_consistency(model):
    params = random_params(model, batch=3)
    out = model(params)
    single = model(params[1])
    assert torch.allclose(single.vertices[0], out.vertices[1], atol=1e-5)
