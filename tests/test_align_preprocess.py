"""Video -> dataset on a rendered signer (real MediaPipe detections), and the bad inputs around it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from eva_engine.align import PreprocessConfig, PreprocessError, preprocess_video
from eva_engine.cli import app
from eva_engine.data import load_dataset, write_video
from eva_engine.synth import generate


@pytest.fixture(scope="module")
def signer(anny_model, tmp_path_factory):
    """The synthetic wild preset at 256 px, as a video in temporal order, and its dataset."""
    root = tmp_path_factory.mktemp("wild")
    ds = load_dataset(generate("wild", "small", 0, root / "ds", model=anny_model))
    order = sorted(ds.splits["train"] + ds.splits["test_pose"])
    frames = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    video = write_video(root / "signer.mp4", frames, fps=10)
    return ds, order, frames, video


@pytest.fixture(scope="module")
def preprocessed(signer, anny_model, tmp_path_factory):
    _, _, _, video = signer
    out = tmp_path_factory.mktemp("pre") / "ds"
    report = preprocess_video(video, out, PreprocessConfig(test_every=4), model=anny_model)
    return report, load_dataset(out)


def test_writes_a_dataset_with_detections_and_fitted_params(signer, preprocessed, anny_model):
    ds_truth, order, frames, _ = signer
    report, ds = preprocessed
    assert report.kept_frames == len(frames) and report.dropped_frames == 0
    assert ds.meta.source == "video" and ds.meta.camera_source == "estimated"
    assert ds.meta.params_source == "fitted" and ds.meta.keypoints_source == "mediapipe"
    assert ds.meta.body_model == "anny" and ds.params.batch_size == len(frames)
    extras = {"hand_depth", "pose_world", "face_mesh", "face_depth", "hand_confidence"}
    assert set(ds.keypoint_extras) == extras
    assert ds.splits["test_pose"] == [3, 7, 11] and len(ds.splits["train"]) == 9
    assert report.detection_rates["pose"] == 1.0 and report.detection_rates["face"] == 1.0
    assert min(report.detection_rates["left_hand"], report.detection_rates["right_hand"]) >= 0.5
    # The fit at least halves the hands' reprojection error (what its hand stages are for) and
    # lowers the rest.
    assert report.reprojection_fitted["hands"] < 0.5 * report.reprojection_initial["hands"]
    assert report.reprojection_fitted["body"] < report.reprojection_initial["body"]
    # The person mask (holistic segmentation) agrees with the rendered person.
    for j in (0, 5, 11):
        mine = ds.mask(j) > 0.5
        truth = ds_truth.mask(order[j]) > 0.5
        iou = (mine & truth).sum() / (mine | truth).sum()
        assert iou > 0.7, (j, float(iou))
    # Detections land on the rendered body: detected wrists near the true projected wrists.
    gt = ds_truth.gt_keypoints[order]
    for name in ("left_wrist", "right_wrist", "nose"):
        k = list(ds.keypoint_names).index(name)
        err = (ds.keypoints[:, k, :2] - gt[:, k, :2]).norm(dim=-1)
        assert err.median() < 8.0, (name, err)


def test_detections_made_on_larger_frames_land_on_the_dataset_frames(signer, anny_model, tmp_path):
    ds_truth, order, frames, video = signer
    config = PreprocessConfig(max_size=128, detect_max_size=256, fit=False)
    report = preprocess_video(video, tmp_path / "ds", config, model=anny_model)
    ds = load_dataset(tmp_path / "ds")
    assert ds.meta.image_size == (128, 128) and report.kept_frames == len(frames)
    assert ds.mask(0).shape == (128, 128)
    gt = ds_truth.gt_keypoints[order][..., :2] * 0.5  # the truth at 256 px, in 128 px frames
    for name in ("left_wrist", "right_wrist", "nose"):
        k = list(ds.keypoint_names).index(name)
        err = (ds.keypoints[:, k, :2] - gt[:, k]).norm(dim=-1)
        assert err.median() < 4.0, (name, err)


def test_face_close_ups_come_from_the_larger_video(signer, preprocessed, tmp_path):
    """The dataset frames are the 256 px video itself: a close-up would add nothing, so none was
    stored. From the same frames twice as large, each frame with a face gets one, cut around
    the stored face landmarks from the larger frames."""
    import shutil

    import cv2

    from eva_engine.align.preprocess import add_face_crops
    from eva_engine.data.face_crops import FaceCropConfig, cut_crop

    _, _, frames, _ = signer
    report, ds = preprocessed
    assert ds.face_crops is None
    large = np.stack([cv2.resize(f, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC) for f in frames])
    video = write_video(tmp_path / "large.mp4", large, fps=10)
    root = shutil.copytree(report.dataset, tmp_path / "ds")
    crops = add_face_crops(root, video, PreprocessConfig(face_crops=FaceCropConfig(size=128, min_side=4.0)))
    assert crops is not None and crops.frames == list(range(len(frames)))
    # At the larger video's own pixels across the face: no enlarging.
    assert crops.size <= 2 * float(crops.boxes[:, 2].median()) < crops.size + 16
    assert load_dataset(root).face_crops is not None
    marks = ds.keypoint_extras["face_mesh"]
    for i in (0, 6):
        centre = crops.boxes[i, :2] + crops.boxes[i, 2] / 2
        seen = marks[i, :, :2][marks[i, :, 2] > 0]
        assert torch.allclose(centre, (seen.amin(0) + seen.amax(0)) / 2, atol=1e-3)
        cut = cut_crop(large[i], crops.boxes[i].double().numpy(), crops.size, 2.0).astype(np.float32) / 255
        # The video's compression is the only difference.
        assert float(np.abs(crops.image(i).numpy() - cut).mean()) < 0.03
    # Preprocessing the larger video itself cuts them from what it holds in memory: the same
    # squares around its own detections, on every frame.
    config = PreprocessConfig(max_size=256, fit=False, face_crops=FaceCropConfig(size=128, min_side=4.0))
    direct = load_dataset(preprocess_video(video, tmp_path / "direct", config).dataset).face_crops
    assert direct is not None and direct.frames == crops.frames and direct.size == crops.size
    assert float((direct.boxes - crops.boxes).abs().max()) < 0.05 * float(crops.boxes[:, 2].median())


def test_a_detection_resized_keeps_the_view():
    from eva_engine.align.detect import NUM_KEYPOINTS, FrameDetection

    rng = np.random.default_rng(0)
    keypoints = rng.uniform(0, 200, (NUM_KEYPOINTS, 3)).astype(np.float32)
    world = rng.normal(size=(33, 4)).astype(np.float32)
    mesh = rng.uniform(0, 200, (478, 3)).astype(np.float32)
    depth = rng.normal(size=478).astype(np.float32)
    det = FrameDetection(
        keypoints, np.ones(42, np.float32), world, np.ones((100, 200), np.float32), {}, mesh, depth
    )
    small = det.resized((100, 200), (50, 80))
    np.testing.assert_allclose(small.keypoints[:, 0], keypoints[:, 0] * 0.4, rtol=1e-6)
    np.testing.assert_allclose(small.keypoints[:, 1], keypoints[:, 1] * 0.5, rtol=1e-6)
    np.testing.assert_array_equal(small.keypoints[:, 2], keypoints[:, 2])  # confidences
    np.testing.assert_allclose(small.face_mesh[:, :2], mesh[:, :2] * [0.4, 0.5], rtol=1e-6)
    np.testing.assert_allclose(small.hand_depth, 0.4)  # in units of the image width
    np.testing.assert_allclose(small.face_depth, depth * 0.4, rtol=1e-6)
    np.testing.assert_array_equal(small.pose_world, world)  # metric, not in pixels
    assert small.mask.shape == (50, 80) and np.allclose(small.mask, 1.0)
    assert det.resized((100, 200), (100, 200)) is det


def test_region_masks_follow_the_fitted_body_and_the_detections(signer, preprocessed):
    """Each hand's mask from the fitted body lands on that hand's true pixels (the renderer's
    ground truth), only in frames where the detector found the hand, and inside the person."""
    ds_truth, order, _, _ = signer
    _, ds = preprocessed
    assert ds.has_region_masks
    conf = ds.keypoints[..., 2]
    found = {"hand_left": conf[:, 33:54].amax(1) > 0, "hand_right": conf[:, 54:75].amax(1) > 0}
    overlap = {"hand_left": [], "hand_right": [], "face": []}
    for j, i in enumerate(order):
        f, truth = ds[j], ds_truth[i]
        for name, m in f.regions.items():
            assert torch.all(m <= f.mask + 1 / 255)
            if name in found and not found[name][j]:
                assert float(m.sum()) == 0  # a hand the detector missed gets no mask
            elif float(m.sum()) > 0:
                mine, gt = m > 0.5, truth.regions[name] > 0.5
                overlap[name].append(float((mine & gt).sum() / mine.sum().clamp_min(1)))
    for name, values in overlap.items():
        assert values and np.median(values) > 0.5, (name, values)


def test_eval_of_a_preprocessed_video_scores_each_hand_and_the_face(preprocessed, tmp_path):
    from eva_engine.avatar import TrainingRecord, save_avatar
    from eva_engine.train import preset, train_avatar

    _, ds = preprocessed
    result = train_avatar(ds, preset("tiny", iterations=8))
    save_avatar(result.avatar, tmp_path / "avatar", TrainingRecord(train_seconds=result.train_seconds))
    args = ["eval", str(tmp_path / "avatar"), str(ds.root), "--json", str(tmp_path / "m.json")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "m.json").read_text())
    assert set(doc["regions"]) == {"full", "hand", "face"}
    assert doc["regions"]["hand"]["crops"] > doc["regions"]["hand"]["frames"] > 0  # often both hands
    frame = next(iter(doc["per_frame"].values()))
    assert {"hand_left", "hand_right"} & set(frame)
    assert "Hand LPIPS-VGG" in doc["table"]


def test_the_preprocessed_dataset_trains(preprocessed):
    from eva_engine.train import preset, train_avatar

    _, ds = preprocessed
    result = train_avatar(ds, preset("tiny", iterations=8, image_scale=0.25))
    assert len(result.avatar.gaussians.means) > 0
    assert all(np.isfinite(result.losses))


@pytest.mark.parametrize("n", [1, 2])
def test_a_one_or_two_frame_clip_preprocesses_and_trains(signer, anny_model, tmp_path, n):
    """The shortest clips go through the whole job: with a test frame asked every 2nd frame, one
    frame is all training and two split 1 + 1; the avatar trains to finite losses."""
    from eva_engine.align.scaling import scaled_fit_config
    from eva_engine.train import preset, train_avatar

    _, _, frames, _ = signer
    video = write_video(tmp_path / "short.mp4", frames[:n], fps=10)
    config = PreprocessConfig(test_every=2, fitting=scaled_fit_config(0.1))
    report = preprocess_video(video, tmp_path / "ds", config, model=anny_model)
    ds = load_dataset(tmp_path / "ds")
    assert report.kept_frames == n and len(ds.splits["train"]) == 1 and len(ds.splits["test_pose"]) == n - 1
    assert torch.isfinite(ds.params.joints).all()
    result = train_avatar(ds, preset("tiny", iterations=4, image_scale=0.25), body=anny_model)
    assert len(result.avatar.gaussians) > 0 and all(np.isfinite(result.losses))


def test_frames_without_a_person_are_dropped_and_counted(signer, anny_model, tmp_path):
    _, _, frames, _ = signer
    blank = np.full_like(frames[:3], 200)
    video = write_video(tmp_path / "gap.mp4", np.concatenate([frames[:4], blank, frames[4:8]]), fps=10)
    report = preprocess_video(video, tmp_path / "ds", PreprocessConfig(fit=False), model=anny_model)
    assert report.decoded_frames == 11 and report.kept_frames == 8 and report.dropped_frames == 3
    ds = load_dataset(tmp_path / "ds")
    assert len(ds) == 8 and ds.params is None and ds.keypoints.shape == (8, 91, 3)


def test_a_video_without_a_person_is_a_clear_error(tmp_path):
    frames = np.zeros((5, 128, 128, 3), np.uint8)
    frames[:] = np.linspace(0, 255, 128, dtype=np.uint8)[None, None, :, None]
    video = write_video(tmp_path / "empty.mp4", frames, fps=5)
    with pytest.raises(PreprocessError, match="no person"):
        preprocess_video(video, tmp_path / "ds", PreprocessConfig(fit=False))
    assert not (tmp_path / "ds").exists()  # nothing half-written is left behind


def test_cli_errors_are_exit_code_2(tmp_path):
    runner = CliRunner()
    bad = tmp_path / "not-a-video.mp4"
    bad.write_bytes(b"this is not a video")
    res = runner.invoke(app, ["preprocess", str(bad), "--out", str(tmp_path / "ds")])
    assert res.exit_code == 2 and "error" in res.output
    res = runner.invoke(app, ["preprocess", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "ds")])
    assert res.exit_code == 2
    (tmp_path / "exists").mkdir()
    res = runner.invoke(app, ["preprocess", str(bad), "--out", str(tmp_path / "exists")])
    assert res.exit_code == 2 and "exists" in res.output


def test_holistic_face_depths_are_centred_pixels():
    """MediaPipe's face z (units of the image width) becomes pixels relative to the landmarks'
    mean; without a face, depths are zero."""
    from types import SimpleNamespace

    from eva_engine.align.detect import convert_holistic

    rng = np.random.default_rng(0)
    xyz = rng.uniform(0, 1, (478, 3))
    landmarks = SimpleNamespace(landmark=[SimpleNamespace(x=x, y=y, z=z, visibility=0.0) for x, y, z in xyz])
    none = dict(pose_landmarks=None, left_hand_landmarks=None, right_hand_landmarks=None)
    det = convert_holistic(SimpleNamespace(face_landmarks=landmarks, **none), 200, 100)
    np.testing.assert_allclose(det.face_depth, (xyz[:, 2] - xyz[:, 2].mean()) * 200, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(det.face_mesh[:, :2], xyz[:, :2] * [200, 100], rtol=1e-5)
    empty = convert_holistic(SimpleNamespace(face_landmarks=None, **none), 200, 100)
    assert not empty.face_depth.any() and not empty.face_mesh.any()
