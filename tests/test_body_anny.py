"""Anny-specific behaviour: agreement with Anny's own forward, conventions, parts, expression,
keypoint definitions and the cache."""

import socket

import pytest
import torch

from eva_engine.body import KEYPOINT_NAMES, PART_NAMES, AnnyCacheError, ensure_anny_cache, load_body_model
from eva_engine.body.anny_backend import ANNY_TO_WORLD, SEGMENT_LABELS, face_segment_masks
from eva_engine.body.anny_cache import _stale_entries, cache_is_valid, default_cache_dir, expected_cache_file


def kp_index(name: str) -> int:
    return KEYPOINT_NAMES.index(name)


def test_facts(anny_model):
    m = anny_model
    assert m.num_vertices == 13718 and m.num_joints == 104
    assert len(m.faces) == 27420
    assert len(m.expression_names) == 52 and {"jawOpen", "eyeBlinkLeft", "tongueOut"} <= set(
        m.expression_names
    )
    assert m.shape_names == ["gender", "age", "muscle", "weight", "height", "proportions"]
    assert torch.all(m.shape_defaults == 0.5)
    assert {f"finger{i}-{k}.{s}" for i in range(1, 6) for k in range(1, 4) for s in "LR"} <= set(
        m.joint_names
    )
    counts = torch.bincount(m.part_ids, minlength=3)
    assert counts[PART_NAMES.index("hand")] == 2 * 1591
    assert 4000 < counts[PART_NAMES.index("face")] < 5000


def test_own_forward_reproduces_our_vertices(anny_model):
    """Anny's own forward (local-ref 4x4 pose input), fed the equivalent parameters, gives our
    posed vertices and joints (after the boundary rotation): LBS with our transforms matches
    the backend's own posed vertices."""
    g = torch.Generator().manual_seed(1)
    m = anny_model
    p = m.default_params(3)
    p.joints.copy_(torch.randn(p.joints.shape, generator=g) * 0.5)
    p.root_orient.copy_(torch.randn(3, 3, generator=g))
    p.transl.copy_(torch.randn(3, 3, generator=g))
    p.shape.copy_(torch.rand(p.shape.shape, generator=g))
    p.expression.copy_(torch.rand(p.expression.shape, generator=g))
    out = m(p)
    with torch.no_grad():
        ref = m.anny(**m.anny_inputs(p))
    c = ANNY_TO_WORLD.float()
    assert (ref["vertices"] @ c.T - out.vertices).abs().max() <= 1e-5
    assert (ref["bone_poses"][..., :3, 3] @ c.T - out.joints).abs().max() <= 1e-5
    assert (ref["rest_vertices"] @ c.T - m.canonical(p)).abs().max() <= 1e-6


def test_world_convention(anny_model):
    rest = anny_model(anny_model.default_params(1))
    v, kp = rest.vertices[0], anny_model.keypoints(rest)[0]
    height = v[:, 1].max() - v[:, 1].min()
    assert 1.4 < height < 1.9  # metres, Y up
    assert v[:, 1].argmax() in anny_model.part_vertex_ids("face")  # top of the head is up
    assert kp[kp_index("nose"), 2] > v[anny_model.part_vertex_ids("face"), 2].mean()  # faces +Z
    assert kp[kp_index("left_wrist"), 0] > 0.3  # the subject's left is +X


def test_surface_mask_drops_only_hidden_eye_geometry(anny_model):
    m = anny_model
    labels = [SEGMENT_LABELS[i] for i in m.segment_labels.tolist()]
    dropped = {labels[i] for i in torch.nonzero(~m.surface_vertex_mask).squeeze(1).tolist()}
    assert dropped <= {"eye_back.L", "eye_back.R", "eye_cavity.L", "eye_cavity.R"}
    assert 500 < int((~m.surface_vertex_mask).sum()) < 700
    kept = {labels[i] for i in torch.nonzero(m.surface_vertex_mask).squeeze(1).tolist()}
    assert {"eye_front.L", "eye_front.R", "mouth_cavity", "tongue", "head", "hand.L", "body"} <= kept


def test_face_segments_are_annys_own(anny_model):
    """Every label read in one pass is the mask Anny's own function gives for that label."""
    from anny.face_segmentation import get_face_segmentation_mask

    masks = face_segment_masks(anny_model.anny)
    assert masks.shape == (anny_model.faces.shape[0], len(SEGMENT_LABELS))
    for i, label in enumerate(SEGMENT_LABELS):
        expected = get_face_segmentation_mask(anny_model.anny, [label]).cpu().numpy()
        assert (masks[:, i] == expected).all() and expected.any(), label


def test_expression_moves_the_face_only(anny_model):
    m = anny_model
    rest = m(m.default_params(1))
    p = m.params_from_pose({"expression": {"jawOpen": 1.0, "eyeBlinkLeft": 1.0}})
    out = m(p)
    kp0, kp1 = m.keypoints(rest)[0], m.keypoints(out)[0]
    lips0 = kp0[kp_index("face_upper_lip_inner"), 1] - kp0[kp_index("face_lower_lip_inner"), 1]
    lips1 = kp1[kp_index("face_upper_lip_inner"), 1] - kp1[kp_index("face_lower_lip_inner"), 1]
    assert lips1 > lips0 + 0.01  # mouth opens by more than a centimetre
    lid = [kp_index("face_left_eye_upper_lid"), kp_index("face_left_eye_lower_lid")]
    rid = [kp_index("face_right_eye_upper_lid"), kp_index("face_right_eye_lower_lid")]
    assert (kp1[lid[0]] - kp1[lid[1]]).norm() < 0.5 * (kp0[lid[0]] - kp0[lid[1]]).norm()  # blink
    assert torch.allclose(kp1[rid], kp0[rid], atol=1e-4)  # the other eye stays open
    moved = (out.vertices[0] - rest.vertices[0]).norm(dim=1) > 1e-4
    assert (m.part_ids[moved] == PART_NAMES.index("face")).float().mean() > 0.95
    # Expression is part of the canonical (rest) shape the transforms apply to.
    assert torch.allclose(m.canonical(p), out.vertices, atol=1e-6)


def test_keypoint_vertices_lie_on_their_parts(anny_model):
    m = anny_model
    w = m.keypoint_regressor.dense_vertex_weights(m.num_vertices)
    for name in KEYPOINT_NAMES:
        row = w[kp_index(name)]
        if row.sum() == 0:
            continue
        parts = m.part_ids[row > 0]
        if name.startswith("face_") or name in ("nose", "left_eye", "right_eye", "mouth_left"):
            assert (parts == PART_NAMES.index("face")).all(), name
        if "_hand_" in name and name.endswith("_tip"):
            assert (parts == PART_NAMES.index("hand")).all(), name


def test_hand_keypoints_follow_the_wrist(anny_model):
    m = anny_model
    p = m.params_from_pose({"joints": {"wrist.L": [0.0, 0.0, 1.0]}})
    kp0 = m.keypoints(m(m.default_params(1)))[0]
    kp1 = m.keypoints(m(p))[0]
    left = [i for i, n in enumerate(KEYPOINT_NAMES) if n.startswith("left_hand_") and n != "left_hand_wrist"]
    right = [i for i, n in enumerate(KEYPOINT_NAMES) if n.startswith("right_hand_")]
    assert (kp1[left] - kp0[left]).norm(dim=1).min() > 0.005
    assert torch.allclose(kp1[right], kp0[right], atol=1e-6)
    # Distances within the rigid palm are kept.
    palm = [kp_index(f"left_hand_{n}") for n in ("index_finger_mcp", "pinky_mcp", "thumb_cmc")]
    assert torch.allclose(torch.pdist(kp1[palm]), torch.pdist(kp0[palm]), atol=1e-3)


def test_cache_is_the_compact_file_only():
    path = expected_cache_file()
    assert path.parent.parent == default_cache_dir()
    assert cache_is_valid(), "run `eva setup` to build the Anny cache"
    assert path.stat().st_size < 120e6


def test_cleaning_the_cache_keeps_the_files_derived_beside_it(tmp_path):
    """`eva setup` removes anny's other data versions and intermediates, not the face-mesh
    correspondence and calibration that live beside the cache (it used to delete both, and every
    `eva setup` rebuilt them)."""
    keep = tmp_path / "v14" / "build_compact_model_data_abc.safetensors"
    keep.parent.mkdir()
    keep.write_bytes(b"x")
    (tmp_path / "v14" / "load_data_abc.safetensors").write_bytes(b"x")
    (tmp_path / "v13").mkdir()
    (tmp_path / "build_model_data_old.safetensors").write_bytes(b"x")
    for name in ("face_mesh_correspondence.json", "face_mesh_calibration.json"):
        (tmp_path / name).write_text("{}")
    (tmp_path / ".build-123").mkdir()
    stale = sorted(p.relative_to(tmp_path).as_posix() for p in _stale_entries(tmp_path, keep))
    assert stale == ["build_model_data_old.safetensors", "v13", "v14/load_data_abc.safetensors"]


def test_missing_or_corrupt_cache_gives_a_clear_message(tmp_path):
    with pytest.raises(AnnyCacheError, match="eva setup"):
        ensure_anny_cache(tmp_path, build_if_missing=False)
    bad = expected_cache_file(tmp_path)
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not a safetensors file")
    assert not cache_is_valid(tmp_path)
    # A truncated copy of the real file is caught by its size, without loading it.
    with expected_cache_file().open("rb") as f:
        bad.write_bytes(f.read(1_000_000))
    assert not cache_is_valid(tmp_path)
    with pytest.raises(AnnyCacheError, match="missing or stale"):
        load_body_model("anny", cache_dir=tmp_path, build_cache=False)


def test_loading_touches_no_network_and_no_global_state(monkeypatch):
    import anny.paths

    before = anny.paths.get_anny_cache_path()

    def no_network(*args, **kwargs):
        raise AssertionError("the body model tried to open a network connection")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr(anny.paths, "download_noncommercial_data", no_network)
    model = load_body_model("anny", build_cache=False)
    assert model.num_vertices == 13718
    assert anny.paths.get_anny_cache_path() == before
