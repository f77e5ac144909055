"""The synthetic benchmark (tiny preset): deterministic, masks exactly the rendered person,
ground truth consistent with the pixels, region masks on hands and face, the split design, and
estimator-like parameter noise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eva_engine.body import KEYPOINT_GROUPS, PART_NAMES
from eva_engine.data import load_dataset, perturb
from eva_engine.data.synthetic import PRESETS, generate, project


@pytest.fixture(scope="module")
def datasets(anny_model, tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    return {p: load_dataset(generate(p, "tiny", 0, root / p, model=anny_model)) for p in PRESETS}


def _dilate(mask: np.ndarray, r: int = 1) -> np.ndarray:
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


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
        uv, _ = project(verts[i : i + 1], f.viewmat, f.K)
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
    if preset == "wild":
        assert not visible[:, 27:33].any()  # ankles, heels, feet below the frame
    else:
        assert visible[:, :33].all()


@pytest.mark.parametrize("preset", list(PRESETS))
def test_region_masks_hold_hand_and_face_pixels(datasets, preset, anny_model):
    ds = datasets[preset]
    assert ds.meta.has_region_masks
    hand_hits, face_hits = [], []
    for i in range(len(ds)):
        f = ds[i]
        assert torch.all(f.hand_mask <= f.mask + 1.5 / 255) and torch.all(f.face_mask <= f.mask + 1.5 / 255)
        assert f.hand_mask.sum() > 3 and f.face_mask.sum() > 3
        hand = _dilate(f.hand_mask.numpy() > 0, 2)
        face = _dilate(f.face_mask.numpy() > 0, 1)
        kp = ds.gt_keypoints[i]
        for group, hits, m in (
            ("left_hand", hand_hits, hand),
            ("right_hand", hand_hits, hand),
            ("face", face_hits, face),
        ):
            k = kp[KEYPOINT_GROUPS[group]]
            k = k[k[:, 2] > 0]
            hits += list(m[k[:, 1].long(), k[:, 0].long()])
    # Hand points may be hidden behind the other hand or the body; most are on hand pixels.
    assert np.mean(hand_hits) > 0.8, np.mean(hand_hits)
    assert np.mean(face_hits) > 0.95, np.mean(face_hits)
    assert PART_NAMES == ("body", "hand", "face")


def test_splits_and_what_the_pipeline_gets(datasets):
    wild, ctrl = datasets["wild"], datasets["controlled"]
    for ds in (wild, ctrl):
        s = ds.splits
        assert len(ds) == 15 and ds.image_size == (96, 96)
        assert s["test_pose"] == [2, 5, 8, 11] and len(s["train"]) == 8 and s["test_view"] == [12, 13, 14]
        assert not set(s["train"]) & set(s["test_pose"]) and not set(s["train"]) & set(s["test_view"])
        # Same static camera for the sequence; the held-out view is elsewhere and shows training poses.
        assert torch.equal(ds.viewmat[0], ds.viewmat[11]) and not torch.allclose(
            ds.viewmat[0], ds.viewmat[12]
        )
        src = ds.meta.extra["pose_of_frame"]
        assert all(src[i] in s["train"] for i in s["test_view"])
        assert torch.equal(ds.gt_params.joints[12], ds.gt_params.joints[src[12]])
        assert ds.meta.body_model == "anny" and ds.meta.source == "synthetic"
    assert wild.params is None and wild.keypoints is None and wild.gt_params is not None
    assert ctrl.params is not None and ctrl.meta.params_source == "ground_truth"
    assert torch.equal(ctrl.params.joints, ctrl.gt_params.joints)
    # The motion moves: arms, fingers and the face change over the clip.
    j = wild.gt_params.joints
    assert (j[:12] - j[:1]).abs().amax() > 0.3
    assert wild.gt_params.expression[:12].std(0).max() > 0.05


def test_perturb_imitates_an_estimator(datasets, anny_model):
    gt = datasets["controlled"].gt_params
    names = anny_model.pose_joint_names
    assert all(torch.equal(a, b) for a, b in zip(perturb(gt, 0.0, model=anny_model).tensors().values(),
                                                 gt.tensors().values(), strict=True))  # fmt: skip
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
    from eva_engine.data.preview import contact_sheet

    ds = datasets["wild"]
    # The held-out camera sits 35 deg about the vertical axis from the training camera.
    centres = [-(v[:3, :3].T @ v[:3, 3]) for v in (ds.viewmat[0], ds.viewmat[12])]
    target = torch.tensor([0.0, centres[0][1], 0.0])
    a, b = (c - target for c in centres)
    angle = torch.rad2deg(torch.acos((a @ b) / (a.norm() * b.norm())))
    assert float(angle) == pytest.approx(ds.meta.extra["view_angle_deg"], abs=1.0)
    sheet = contact_sheet(ds, [0, 12], tile=32)
    assert sheet.shape == (64, 128, 3) and sheet.dtype == np.uint8
    # Every close-up shows the person, not just background.
    tiles = sheet.reshape(2, 32, 4, 32, 3).transpose(0, 2, 1, 3, 4)
    assert (tiles.reshape(8, -1).astype(int) < 250).any(axis=1).all()
