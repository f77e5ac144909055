"""Rendered face close-ups of a synthetic dataset (``eva_engine.synth.face_crops``): the close-up
is the frame's square around the face at more pixels, its mask is the person's, and a face too
small for one gets none."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eva_engine.align.face_mesh import load_correspondence
from eva_engine.data import load_dataset
from eva_engine.data.face_crops import FaceCropConfig, cut_crop
from eva_engine.eval.expression_fidelity import fitted_landmarks
from eva_engine.synth import generate
from eva_engine.synth.face_crops import render_face_crops

CONFIG = FaceCropConfig(size=64, min_side=8.0)


@pytest.fixture(scope="module")
def dataset(anny_model, tmp_path_factory):
    path = generate("controlled", "tiny", 0, tmp_path_factory.mktemp("synth") / "ds", model=anny_model)
    ds = load_dataset(path)
    reg, ids = load_correspondence(anny_model).regressor(anny_model)
    return ds, fitted_landmarks(anny_model, ds.gt_params, reg, ids, ds.K, ds.viewmat)


def to_uint8(t: torch.Tensor) -> np.ndarray:
    return (t.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def test_close_ups_are_the_frames_faces_at_more_pixels(dataset, anny_model):
    import cv2

    ds, face_mesh = dataset
    crops = render_face_crops(ds.root, face_mesh, model=anny_model, config=CONFIG)
    assert crops is not None and crops.size == CONFIG.size
    assert crops.frames == list(range(ds.meta.num_frames))
    assert load_dataset(ds.root).face_crops is not None  # stored with the dataset

    def error(i: int, j: int) -> float:
        """Close-up ``i`` blurred to the frame's detail against frame ``j``'s square ``i`` scaled up."""
        box = crops.boxes[i].double().numpy()
        gain = crops.size / box[2]
        close = cv2.GaussianBlur(to_uint8(crops.image(i)), (0, 0), 0.5 * gain).astype(np.float32)
        frame = cut_crop(to_uint8(ds[j].image), box, crops.size, 1.0).astype(np.float32)
        return float(np.abs(close - frame).mean() / 255.0)

    for i in crops.frames[:3]:
        other = (i + len(ds) // 2) % len(ds)
        assert error(i, i) < 0.03 and error(i, i) < 0.5 * error(i, other), (error(i, i), error(i, other))
        # The person's mask: opaque at the face's centre, background in a corner.
        c = crops.size // 2
        assert float(crops.mask(i)[c - 3 : c + 3, c - 3 : c + 3].mean()) > 0.95


def test_no_close_ups_for_faces_too_small(dataset, anny_model):
    ds, face_mesh = dataset
    assert render_face_crops(ds.root, face_mesh, model=anny_model, config=CONFIG) is not None
    too_small = FaceCropConfig(size=64, min_side=1e4)
    assert render_face_crops(ds.root, face_mesh, model=anny_model, config=too_small) is None
    assert not (ds.root / "face_crops").exists()  # the older ones removed, nothing partial left
    assert not [p for p in ds.root.iterdir() if p.name.startswith(".face_crops")]


def test_no_close_up_of_a_face_the_frame_cuts(dataset, anny_model):
    """A face partly outside its frame (here: moved up by half its height) is one a detector
    would not find in a video: that frame gets no close-up, the others keep theirs."""
    ds, face_mesh = dataset
    moved = face_mesh.clone()
    height = float(face_mesh[0, :, 1].max() - face_mesh[0, :, 1][face_mesh[0, :, 2] > 0].min())
    moved[0, :, 1] -= float(face_mesh[0, :, 1][face_mesh[0, :, 2] > 0].min()) + 0.5 * height
    crops = render_face_crops(ds.root, moved, model=anny_model, config=CONFIG)
    assert crops is not None and crops.frames == list(range(1, ds.meta.num_frames))


def test_only_for_synthetic_datasets_with_their_truth(dataset, anny_model, tmp_path):
    ds, face_mesh = dataset
    with pytest.raises(ValueError, match="frames"):
        render_face_crops(ds.root, face_mesh[:2], model=anny_model, config=CONFIG)
    import json
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(ds.root, copy)
    meta = json.loads((copy / "meta.json").read_text())
    meta["extra"]["generator"] = "a video"
    (copy / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="not a synthetic benchmark dataset"):
        render_face_crops(copy, face_mesh, model=anny_model, config=CONFIG)
