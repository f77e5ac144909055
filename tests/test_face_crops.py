"""Face close-ups: the crop camera and the cut crop agree with a render at the video's size,
they are written and read back with the dataset, small videos get none, and training uses them
as a second view."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers.scenes import front_camera, teacher_scene

from eva_engine.data.face_crops import (
    FaceCropConfig,
    crop_boxes,
    crop_intrinsics,
    cut_crop,
    load_face_crops,
    write_face_crops,
)
from eva_engine.render import Camera
from eva_engine.train import preset, train_avatar
from eva_engine.train.face_views import FaceViewConfig, FaceViews

SIZE, SCALE, CROP = 56, 4, 64


@pytest.fixture(scope="module")
def scene(anny_model):
    return teacher_scene(anny_model, n_frames=6, size=SIZE)


def face_landmarks(ds) -> torch.Tensor:
    """[N, 478, 3] stand-in face-mesh landmarks: a grid over each frame's face region (the
    close-ups need only their extent)."""
    marks = torch.zeros(len(ds), 478, 3)
    for i in range(len(ds)):
        ys, xs = torch.nonzero(ds[i].regions["face"] > 0.5, as_tuple=True)
        if len(xs) == 0:
            continue
        t = torch.linspace(0, 1, 478)
        marks[i, :, 0] = xs.min() + t * (xs.max() + 1 - xs.min())
        marks[i, :, 1] = ys.min() + t.flip(0) * (ys.max() + 1 - ys.min())
        marks[i, :, 2] = 1.0
    return marks


def large_render(teacher, params, scale: int) -> np.ndarray:
    """The frame's render at ``scale`` times its size (what a larger video holds), uint8."""
    cam = front_camera(SIZE)
    K = cam.K.clone()
    K[:2] *= scale
    big = Camera(K, cam.viewmat, SIZE * scale, SIZE * scale)
    with torch.no_grad():
        img = teacher(params, big, torch.ones(3)).image.clamp(0, 1)
    return (img.numpy() * 255 + 0.5).astype(np.uint8)


@pytest.fixture(scope="module")
def crops(scene, tmp_path_factory):
    ds, teacher = scene
    root = tmp_path_factory.mktemp("ds")
    frames = ((large_render(teacher, ds.params[i], SCALE), float(i)) for i in range(len(ds)))
    masks = torch.stack([ds[i].mask for i in range(len(ds))])
    cfg = FaceCropConfig(size=CROP, min_side=4.0)
    written = write_face_crops(root, frames, torch.arange(len(ds)).double(), face_landmarks(ds), masks, cfg)
    return root, written


def test_crop_camera_renders_the_cut_crop(scene, crops):
    """The close-up's camera (crop_intrinsics) sees what cut_crop takes from the larger render."""
    ds, teacher = scene
    _, fc = crops
    i = fc.frames[0]
    K = crop_intrinsics(ds[i].K, fc.boxes[i], fc.size)
    with torch.no_grad():
        direct = teacher(ds.params[i], Camera(K, ds[i].viewmat, fc.size, fc.size), torch.ones(3)).image
    cut = cut_crop(large_render(teacher, ds.params[i], SCALE), fc.boxes[i].double().numpy(), fc.size, SCALE)
    err = (direct.clamp(0, 1) - torch.from_numpy(cut).float() / 255).abs()
    assert float(err.mean()) < 0.02, float(err.mean())
    # The stored image is that cut; the mask covers the face.
    assert float((fc.image(i) - torch.from_numpy(cut).float() / 255).abs().max()) < 1.5 / 255
    c = fc.size // 2
    assert float(fc.mask(i)[c - 4 : c + 4, c - 4 : c + 4].mean()) > 0.9


def test_written_and_read_back(scene, crops):
    ds, _ = scene
    root, fc = crops
    again = load_face_crops(root, len(ds))
    assert again is not None and torch.equal(again.boxes, fc.boxes) and again.size == fc.size
    assert fc.frames == list(range(len(ds)))
    # The video's own pixels across the face (SCALE times the frame's), not more, not CROP.
    side = float(fc.boxes[:, 2].median())
    assert fc.size % 16 == 0 and SCALE * side - 16 < fc.size <= min(CROP, SCALE * side)
    assert fc.image(0).shape == (fc.size, fc.size, 3) and fc.mask(0).shape == (fc.size, fc.size)
    with pytest.raises(ValueError, match="boxes"):
        load_face_crops(root, len(ds) + 1)
    assert load_face_crops(root / "nowhere", len(ds)) is None


def test_boxes_skip_frames_without_a_face():
    marks = torch.zeros(3, 478, 3)
    marks[1, :, :2] = torch.rand(478, 2) * 40 + 10
    marks[1, :, 2] = 1.0
    marks[2, :, :2] = torch.rand(478, 2) * 3  # a face 3 px across: too small
    marks[2, :, 2] = 1.0
    boxes = crop_boxes(marks, (64, 64), FaceCropConfig())
    assert boxes[0, 2] == 0 and boxes[2, 2] == 0
    assert boxes[1, 2] == pytest.approx(
        1.6 * float((marks[1, :, :2].amax(0) - marks[1, :, :2].amin(0)).amax())
    )


def test_no_close_ups_from_a_video_no_larger_than_the_frames(scene, tmp_path):
    """A video decoded at the frames' own size holds nothing a close-up would add: none are
    written, and a dataset's older ones are removed."""
    ds, teacher = scene
    frames = [(large_render(teacher, ds.params[i], 1), float(i)) for i in range(len(ds))]
    masks = torch.stack([ds[i].mask for i in range(len(ds))])
    (tmp_path / "face_crops").mkdir()
    cfg = FaceCropConfig(size=CROP, min_side=4.0)
    got = write_face_crops(
        tmp_path, iter(frames), torch.arange(len(ds)).double(), face_landmarks(ds), masks, cfg
    )
    assert got is None and not (tmp_path / "face_crops").exists()
    assert not list(tmp_path.iterdir())  # no partial folder left behind


def test_training_with_face_views(scene, crops, anny_model):
    ds, _ = scene
    _, fc = crops
    with_crops = dataclasses.replace(ds)
    with_crops.face_crops = fc
    views = FaceViews.load(with_crops, ds.splits["train"], torch.device("cpu"))
    assert views is not None and len(views) == len(ds.splits["train"])
    cam, target, mask = views.view(0, torch.ones(3))
    s = fc.size
    assert target.shape == (s, s, 3) and mask.shape == (s, s) and cam.width == s
    cfg = preset("tiny", iterations=12, face_view=FaceViewConfig(weight=1.0, every=2))
    result = train_avatar(with_crops, cfg, body=anny_model)
    assert all(np.isfinite(result.losses)) and result.timings["face_view"] > 0
    # With ``densify`` the close-ups' gradients reach density control: the first refinement
    # (step 4, the window moved up) sees more candidates than the frames' alone.
    window = {"refine_start_iter": 4, "refine_every": 4}
    early = dataclasses.replace(cfg, strategy=dataclasses.replace(cfg.strategy, **window))
    counts = []
    for densify in (False, True):
        face = FaceViewConfig(weight=1.0, densify=densify)
        run = train_avatar(with_crops, dataclasses.replace(early, face_view=face), body=anny_model)
        first = run.refinements[0]
        counts.append(first["cloned"] + first["split"])
    assert counts[1] > counts[0], counts
    # Off (the default) or without close-ups, the step has no second view.
    plain = train_avatar(ds, dataclasses.replace(cfg, face_view=FaceViewConfig(weight=1.0)), body=anny_model)
    assert plain.timings["face_view"] == 0


def test_config_checks():
    with pytest.raises(ValueError):
        FaceCropConfig(size=8)
    with pytest.raises(ValueError):
        FaceCropConfig(pad=0.5)
    with pytest.raises(ValueError):
        FaceViewConfig(weight=-1)
    with pytest.raises(ValueError):
        FaceViewConfig(every=0)
