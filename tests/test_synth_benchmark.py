"""The synthetic benchmark (tiny preset): deterministic, masks exactly the rendered person,
ground truth consistent with the pixels, region masks on hands and face, the split design, and
estimator-like parameter noise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eva_engine.body import KEYPOINT_GROUPS, PART_NAMES
from eva_engine.data import load_dataset, perturb
from eva_engine.geometry import project_points, to_camera
from eva_engine.synth.benchmark import PRESETS, SIZES, generate
from eva_engine.synth.motion import FACE_ACTIONS, MotionConfig, sign_motion
from eva_engine.synth_names import SYNTH_PRESETS, SYNTH_SIZES


@pytest.fixture(scope="module")
def datasets(anny_model, tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    return {p: load_dataset(generate(p, "tiny", 0, root / p, model=anny_model)) for p in PRESETS}


def _dilate(mask: np.ndarray, r: int = 1) -> np.ndarray:
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


def test_the_named_presets_and_sizes_are_the_defined_ones():
    assert list(PRESETS) == list(SYNTH_PRESETS) and list(SIZES) == list(SYNTH_SIZES)


def test_deterministic_by_seed(anny_model, datasets, tmp_path):
    again = load_dataset(generate("wild", "tiny", 0, tmp_path / "again", model=anny_model))
    first = datasets["wild"]
    assert torch.equal(first.images(), again.images())
    assert torch.equal(first.masks(), again.masks())
    for name, t in first.gt_params.tensors().items():
        assert torch.equal(t, getattr(again.gt_params, name))
    other = load_dataset(generate("wild", "tiny", 1, tmp_path / "other", model=anny_model))
    assert not torch.equal(first.gt_params.joints, other.gt_params.joints)
    assert not torch.equal(first.gt_params.shape, other.gt_params.shape)
    with pytest.raises(FileExistsError):
        generate("wild", "tiny", 0, tmp_path / "again", model=anny_model)
    with pytest.raises(ValueError, match="unknown preset"):
        generate("studio", "tiny", 0, tmp_path / "x", model=anny_model)


@pytest.mark.parametrize("preset", list(PRESETS))
def test_mask_is_exactly_the_rendered_person(datasets, preset, anny_model):
    ds = datasets[preset]
    bg = torch.tensor(ds.meta.background)
    verts = anny_model(ds.gt_params).vertices
    for i in range(len(ds)):
        f = ds[i]
        person = f.mask > 0
        # Outside the mask the image is exactly the background; every non-background pixel is masked.
        assert torch.all(f.image[~person] == bg)
        assert torch.all(person[(f.image - bg).abs().amax(-1) > 1.5 / 255])
        # The mask is where the posed body projects: every projected vertex inside the image
        # lands on the mask, and the mask covers no more than the projected body's extent.
        uv = project_points(to_camera(verts[i : i + 1], f.viewmat), f.K)
        px = uv[0].floor().long().numpy()
        h, w = ds.image_size
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        m = _dilate(person.numpy())
        assert m[px[inside, 1], px[inside, 0]].mean() > 0.995
        drawn = np.zeros((h, w), bool)
        drawn[px[inside, 1], px[inside, 0]] = True
        assert (person.numpy() & ~_dilate(drawn, 2)).sum() == 0


@pytest.mark.parametrize("preset", list(PRESETS))
def test_keypoints_project_inside_the_mask(datasets, preset):
    ds = datasets[preset]
    kp = ds.gt_keypoints
    assert kp.shape == (len(ds), 91, 3)
    hits = []
    for i in range(len(ds)):
        m = _dilate(ds.mask(i).numpy() > 0)
        k = kp[i][kp[i, :, 2] > 0]
        hits += list(m[k[:, 1].long(), k[:, 0].long()])
    assert np.mean(hits) > 0.97, np.mean(hits)
    # Confidence 0 exactly for points outside the image (waist-up framing cuts the legs).
    visible = kp[..., 2] > 0
    h, w = ds.image_size
    assert torch.all((kp[..., 0] >= 0) & (kp[..., 0] < w) & (kp[..., 1] >= 0) & (kp[..., 1] < h) == visible)
    assert not visible[:, 27:33].any()  # ankles, heels, feet below the frame (waist / thighs up)
    if preset == "controlled":
        assert visible[:, 23:27].all()  # hips and knees in view


@pytest.mark.parametrize("preset", list(PRESETS))
def test_region_masks_hold_each_hand_and_the_face(datasets, preset):
    ds = datasets[preset]
    assert ds.has_region_masks
    hits = {"hand_left": [], "hand_right": [], "face": []}
    misses = {"hand_left": [], "hand_right": []}
    for i in range(len(ds)):
        f = ds[i]
        for m in f.regions.values():
            assert torch.all(m <= f.mask + 1.5 / 255)  # a part of the person
        assert f.regions["face"].sum() > 3
        kp = ds.gt_keypoints[i]
        masks = {r: _dilate(m.numpy() > 0, 2 if r != "face" else 1) for r, m in f.regions.items()}
        for group, region in (("left_hand", "hand_left"), ("right_hand", "hand_right"), ("face", "face")):
            k = kp[KEYPOINT_GROUPS[group]]
            k = k[k[:, 2] > 0]
            hits[region] += list(masks[region][k[:, 1].long(), k[:, 0].long()])
        # Each hand's keypoints are on its own mask, not on the other hand's (unless the hands touch).
        for group, other in (("left_hand", "hand_right"), ("right_hand", "hand_left")):
            k = kp[KEYPOINT_GROUPS[group]]
            k = k[k[:, 2] > 0]
            misses[other] += list(masks[other][k[:, 1].long(), k[:, 0].long()])
    # Hand points may be hidden behind the other hand or the body; most are on their hand's pixels.
    for region in ("hand_left", "hand_right"):
        assert np.mean(hits[region]) > 0.8, (region, np.mean(hits[region]))
        assert np.mean(misses[region]) < 0.2, (region, np.mean(misses[region]))
    assert np.mean(hits["face"]) > 0.95, np.mean(hits["face"])
    assert PART_NAMES == ("body", "hand", "face")


def test_splits_and_what_the_pipeline_gets(datasets):
    wild, ctrl = datasets["wild"], datasets["controlled"]
    # controlled (XHumans): train on take 0, test on another take, held-out views of training poses
    s, takes = ctrl.splits, ctrl.meta.extra["take_of_frame"]
    assert len(ctrl) == 18 and ctrl.image_size == (96, 96)
    assert s["train"] == list(range(12)) and s["test_pose"] == [12, 13, 14] and s["test_view"] == [15, 16, 17]
    assert {takes[i] for i in s["train"]} == {0} and {takes[i] for i in s["test_pose"]} == {1}
    # wild (UPB): alternate frames of one take
    s = wild.splits
    assert len(wild) == 15 and s["test_pose"] == [1, 3, 5, 7, 9, 11] and s["train"] == [0, 2, 4, 6, 8, 10]
    assert set(wild.meta.extra["take_of_frame"]) == {0}
    for ds in (wild, ctrl):
        s = ds.splits
        assert not set(s["train"]) & set(s["test_pose"]) and not set(s["train"]) & set(s["test_view"])
        # Same static camera for the sequence; the held-out view is elsewhere and shows training poses.
        view = s["test_view"][0]
        assert torch.equal(ds.viewmat[0], ds.viewmat[s["test_pose"][-1]])
        assert not torch.allclose(ds.viewmat[0], ds.viewmat[view])
        src = ds.meta.extra["pose_of_frame"]
        assert all(src[i] in s["train"] for i in s["test_view"])
        assert torch.equal(ds.gt_params.joints[view], ds.gt_params.joints[src[view]])
        assert ds.meta.body_model == "anny" and ds.meta.source == "synthetic"
    assert wild.params is None and wild.keypoints is None and wild.gt_params is not None
    assert ctrl.params is not None and ctrl.meta.params_source == "ground_truth"
    assert torch.equal(ctrl.params.joints, ctrl.gt_params.joints)
    # The motion moves: arms, fingers and the face change over the clip.
    j = wild.gt_params.joints
    assert (j[:12] - j[:1]).abs().amax() > 0.3
    assert wild.gt_params.expression[:12].std(0).max() > 0.05
    # The test take is another motion, not frames of the training one.
    assert (ctrl.gt_params.joints[12] - ctrl.gt_params.joints[0]).abs().amax() > 0.1


def test_training_take_keeps_held_out_expressions_out(datasets, anny_model):
    """The training take draws from a subset of the facial actions; other takes from all, so a
    test take shows expressions the avatar never saw."""
    ctrl = datasets["controlled"]
    held = ctrl.meta.extra["held_out_face_actions"]
    assert (
        held
        and ctrl.meta.extra["motion"][0]["face_actions"] == [a for a in FACE_ACTIONS if a not in held]
        and ctrl.meta.extra["motion"][1]["face_actions"] == list(FACE_ACTIONS)
    )
    cols = [anny_model.expression_names.index(a) for a in held]
    assert ctrl.gt_params.expression[ctrl.splits["train"]][:, cols].abs().max() == 0
    # Densely sampled, another take of the same subject shows them.
    times = np.linspace(0, 6, 121)
    cfg = MotionConfig(face_actions=FACE_ACTIONS)
    test_take = sign_motion(anny_model, ctrl.gt_params.shape[:1], times, seed=0, cfg=cfg, take=1)
    assert test_take.expression[:, cols].max() > 0.3
    with pytest.raises(ValueError, match="face_actions"):
        sign_motion(anny_model, ctrl.gt_params.shape[:1], times, 0, MotionConfig(face_actions=("frown",)))


def test_shading_follows_a_world_light_and_has_highlights(anny_model, tmp_path):
    """The benchmark's light is fixed in the world (shading changes when the body turns) and
    glossy surfaces get a highlight that a matte render lacks."""
    from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer

    params = anny_model.default_params(2)
    params.root_orient[1, 1] = 0.8  # the second frame turns the body
    verts = anny_model(params).vertices
    K = torch.tensor([[120.0, 0, 48], [0, 120.0, 48], [0, 0, 1]])
    view = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
    view[:3, 3] = torch.tensor([0.0, 0.3, 2.5])
    faces = anny_model.faces
    colors = np.full((anny_model.num_vertices, 3), 0.6, np.float32)
    shaded = {}
    for frame in ("camera", "world"):
        cfg = MeshRenderConfig(width=96, height=96, light_frame=frame, light=(-0.35, 0.55, 1.0))
        with MeshRenderer(faces, cfg, num_vertices=anny_model.num_vertices) as r:
            r.set_surface(colors=colors)
            shaded[frame] = [r.render(verts[i], view, K).rgb for i in range(2)]
            # A texture with gloss (alpha) adds a highlight over the same albedo.
            uv = np.zeros((anny_model.num_vertices, 2), np.float32)
            albedo = np.full((4, 4, 3), 0.6)
            matte, glossy = (np.concatenate([albedo, np.full((4, 4, 1), a)], -1) for a in (0.0, 1.0))
            r.set_surface(texture=matte, uv=uv)
            m = r.render(verts[0], view, K).rgb
            r.set_surface(texture=glossy, uv=uv)
            g = r.render(verts[0], view, K).rgb
            assert torch.all(g >= m - 1e-6) and (g - m).max() > 0.2
    # Same frames, another light frame: different shading (the world light is not the camera's).
    assert (shaded["camera"][0] - shaded["world"][0]).abs().max() > 0.05


def test_perturb_imitates_an_estimator(datasets, anny_model):
    gt = datasets["controlled"].gt_params
    names = anny_model.pose_joint_names
    assert all(
        torch.equal(a, b)
        for a, b in zip(
            perturb(gt, 0.0, model=anny_model).tensors().values(), gt.tensors().values(), strict=True
        )
    )
    noisy = perturb(gt, 1.0, model=anny_model, seed=3)
    again = perturb(gt, 1.0, model=anny_model, seed=3)
    assert torch.equal(noisy.joints, again.joints)
    err = (noisy.joints - gt.joints).abs().mean(dim=(0, 2))
    hand = torch.tensor(["finger" in n or "wrist" in n or "metacarpal" in n for n in names])
    assert err[hand].mean() > 2.5 * err[~hand].mean()
    assert (noisy.root_orient - gt.root_orient).abs().max() > 0
    assert noisy.expression.min() >= 0 and noisy.expression.max() <= 1
    assert torch.allclose(
        noisy.shape - gt.shape, (noisy.shape - gt.shape)[:1].expand_as(gt.shape)
    )  # one subject
    worse = perturb(gt, 3.0, model=anny_model, seed=3)
    assert (worse.joints - gt.joints).abs().mean() > (noisy.joints - gt.joints).abs().mean()
    with pytest.raises(ValueError):
        perturb(gt, -1.0, model=anny_model)
    out = anny_model(noisy)
    assert torch.isfinite(out.vertices).all()


def test_held_out_view_and_contact_sheet(datasets):
    from eva_engine.synth.contact_sheet import contact_sheet

    ds = datasets["wild"]
    # The held-out camera sits 35 deg about the vertical axis from the training camera.
    view = ds.splits["test_view"][0]
    centres = [-(v[:3, :3].T @ v[:3, 3]) for v in (ds.viewmat[0], ds.viewmat[view])]
    target = torch.tensor([0.0, centres[0][1], 0.0])
    a, b = (c - target for c in centres)
    angle = torch.rad2deg(torch.acos((a @ b) / (a.norm() * b.norm())))
    assert float(angle) == pytest.approx(ds.meta.extra["view_angle_deg"], abs=1.0)
    sheet = contact_sheet(ds, [0, view], tile=32)
    assert sheet.shape == (64, 128, 3) and sheet.dtype == np.uint8
    # Every close-up shows the person, not just background.
    tiles = sheet.reshape(2, 32, 4, 32, 3).transpose(0, 2, 1, 3, 4)
    assert (tiles.reshape(8, -1).astype(int) < 250).any(axis=1).all()


def test_novel_preset_tests_beyond_the_training_range(datasets, anny_model):
    """``novel``: training keeps the elbows below the shoulders, the far take raises them; held-out
    views show training (or far) poses from 35 and 70 deg; every test frame records its novelty."""
    ds = datasets["novel"]
    s, extra = ds.splits, ds.meta.extra
    takes, views, pose_of = extra["take_of_frame"], extra["view_deg_of_frame"], extra["pose_of_frame"]
    assert {takes[i] for i in s["train"]} == {0} and {takes[i] for i in s["test_pose"]} == {1}
    assert {takes[i] for i in s["test_far_pose"]} == {2}
    assert {views[i] for i in s["test_view"]} == {35.0, 70.0} and {views[i] for i in s["test_far_view"]} == {
        35.0
    }
    assert all(pose_of[i] in s["train"] for i in s["test_view"])
    assert all(pose_of[i] in s["test_far_pose"] for i in s["test_far_view"])
    assert all(views[i] == 0.0 for name in ("train", "test_pose", "test_far_pose") for i in s[name])
    # Elbow height over the shoulder joint, both arms: always below in training, above in the far take.
    joints = anny_model(ds.gt_params).joints
    names = anny_model.joint_names
    lift = torch.stack(
        [
            joints[:, names.index(f"lowerarm01.{side}"), 1] - joints[:, names.index(f"upperarm01.{side}"), 1]
            for side in "LR"
        ],
        dim=1,
    ).amax(dim=1)
    assert (
        lift[s["train"]].max() < 0 and lift[s["test_pose"]].max() < 0 and lift[s["test_far_pose"]].max() > 0
    )
    # Novelty: a held-out view shows its training pose exactly, its camera turned by the view angle.
    novelty = {int(k): v for k, v in extra["novelty"].items()}
    tested = [i for name in ("test_pose", "test_view", "test_far_pose", "test_far_view") for i in s[name]]
    assert sorted(novelty) == sorted(tested)
    for i in s["test_view"]:
        src = pose_of[i]
        assert novelty[i]["pose_deg"] == 0.0 and novelty[i]["nearest_train"] == src
        body_yaw = float(torch.rad2deg(ds.gt_params.root_orient[src, 1]))
        assert novelty[i]["yaw_deg"] == pytest.approx(views[i] - body_yaw, abs=3.0)
    for i in s["test_far_view"]:
        assert novelty[i]["pose_deg"] == novelty[pose_of[i]]["pose_deg"]
    near = [novelty[i]["pose_deg"] for i in s["test_pose"]]
    far = [novelty[i]["pose_deg"] for i in s["test_far_pose"]]
    assert min(near) > 0 and max(far) > max(near) + 20


def test_wild_gt_is_wild_with_the_ground_truth_given(datasets):
    """The paper's regime benchmark: wild's frames and split, with the ground truth as inputs."""
    wild, given = datasets["wild"], datasets["wild-gt"]
    assert wild.params is None and given.params is not None
    assert given.splits == wild.splits and len(given) == len(wild)
    for i in (0, len(wild) - 1):
        assert torch.equal(given[i].image, wild[i].image) and torch.equal(given[i].K, wild[i].K)
    for name, value in given.params.tensors().items():
        assert torch.equal(value, getattr(given.gt_params, name)), name
    assert given.meta.params_source == "ground_truth"
