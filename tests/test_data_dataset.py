"""The dataset layout: the loader returns exactly what the writer wrote; bad folders give
DatasetError; an existing dataset is never overwritten by accident."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from eva_engine.body import BodyParams
from eva_engine.data import DatasetError, DatasetMeta, DatasetWriter, ParamNames, load_dataset

N, H, W, P, E, S, K = 5, 12, 10, 4, 3, 2, 6


def _params(seed: int) -> BodyParams:
    g = torch.Generator().manual_seed(seed)
    return BodyParams(
        root_orient=torch.randn(N, 3, generator=g),
        transl=torch.randn(N, 3, generator=g),
        joints=torch.randn(N, P, 3, generator=g),
        expression=torch.rand(N, E, generator=g),
        shape=torch.rand(N, S, generator=g),
    )


NAMES = ParamNames([f"j{i}" for i in range(P)], [f"e{i}" for i in range(E)], [f"s{i}" for i in range(S)])


def write_sample(root, regions=True, params=True, overwrite=False):
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (N, H, W, 3), dtype=np.uint8)
    masks = rng.integers(0, 256, (N, H, W), dtype=np.uint8)
    K_ = torch.eye(3).repeat(N, 1, 1) * torch.arange(1, N + 1).view(N, 1, 1).float()
    view = torch.eye(4).repeat(N, 1, 1)
    view[:, 2, 3] = torch.arange(N).float()
    kp = torch.rand(N, K, 3)
    meta = DatasetMeta(
        name="t",
        source="video",
        body_model="anny",
        fps=30.0,
        image_size=(H, W),
        num_frames=0,
        camera_source="estimated",
        extra={"detector": "mediapipe"},
    )
    with DatasetWriter(root, meta, overwrite=overwrite) as w:
        for i in range(N):
            w.add_frame(
                images[i],
                masks[i],
                K=K_[i],
                viewmat=view[i],
                time=0.5 * i,
                regions={"hand_left": masks[i] // 2, "hand_right": masks[i] // 4, "face": masks[i] // 3}
                if regions
                else None,
            )
        out = w.finish(
            {"train": [0, 2, 4], "test_pose": [1, 3]},
            params=_params(1) if params else None,
            params_names=NAMES,
            params_source="fitted",
            keypoints=kp,
            keypoint_names=[f"k{i}" for i in range(K)],
            keypoints_source="mediapipe",
            gt_params=_params(2) if params else None,
        )
    return out, images, masks, K_, view, kp


def test_round_trip(tmp_path):
    root, images, masks, K_, view, kp = write_sample(tmp_path / "ds")
    ds = load_dataset(root)
    assert len(ds) == N and ds.image_size == (H, W)
    assert ds.meta.source == "video" and ds.meta.camera_source == "estimated"
    assert ds.meta.params_source == "fitted" and ds.meta.keypoints_source == "mediapipe"
    assert (
        ds.meta.extra == {"detector": "mediapipe"} and ds.meta.has_region_masks and ds.meta.has_ground_truth
    )
    assert ds.splits == {
        "train": [0, 2, 4],
        "test_pose": [1, 3],
        "test_view": [],
        "test_far_pose": [],
        "test_far_view": [],
    }
    torch.testing.assert_close(ds.K, K_)
    torch.testing.assert_close(ds.viewmat, view)
    torch.testing.assert_close(ds.timestamps, 0.5 * torch.arange(N, dtype=torch.float64))
    torch.testing.assert_close(ds.keypoints, kp)
    assert ds.keypoint_names == [f"k{i}" for i in range(K)] and ds.gt_keypoints is None
    for got, want in ((ds.params, _params(1)), (ds.gt_params, _params(2))):
        for name, t in want.tensors().items():
            torch.testing.assert_close(getattr(got, name), t)
    assert ds.param_names == NAMES
    for i in range(N):
        f = ds[i]
        assert f.image.dtype == torch.float32 and f.image.shape == (H, W, 3)
        np.testing.assert_array_equal((f.image.numpy() * 255).round().astype(np.uint8), images[i])
        np.testing.assert_array_equal((f.mask.numpy() * 255).round().astype(np.uint8), masks[i])
        for name, div in (("hand_left", 2), ("hand_right", 4), ("face", 3)):
            got = (f.regions[name].numpy() * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(got, masks[i] // div)
    assert ds.images([1, 3]).shape == (2, H, W, 3) and ds.masks(region="hand_right").shape == (N, H, W)
    assert ds.meta.version == 2 and ds.has_region_masks


def test_optional_parts_absent(tmp_path):
    root, *_ = write_sample(tmp_path / "ds", regions=False, params=False)
    ds = load_dataset(root)
    assert ds.params is None and ds.gt_params is None and not ds.meta.has_region_masks
    assert ds[0].regions == {}
    with pytest.raises(DatasetError, match="no hand_left masks"):
        ds.mask(0, "hand_left")
    with pytest.raises(ValueError, match="unknown region"):
        ds.mask(0, "hand")


def test_version_1_region_masks_are_not_read_as_per_hand(tmp_path):
    """Version 1 kept both hands in one mask: such a dataset loads, without region masks."""
    root, *_ = write_sample(tmp_path / "ds")
    meta = json.loads((root / "meta.json").read_text())
    (root / "meta.json").write_text(json.dumps({**meta, "version": 1}))
    ds = load_dataset(root)
    assert ds.meta.has_region_masks and not ds.has_region_masks and ds[0].regions == {}
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no partial folder left


def test_never_overwrites_by_accident(tmp_path):
    root, *_ = write_sample(tmp_path / "ds")
    with pytest.raises(FileExistsError):
        write_sample(root)
    write_sample(root, overwrite=True)
    other = tmp_path / "not_a_dataset"
    other.mkdir()
    (other / "precious.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not a dataset"):
        write_sample(other, overwrite=True)
    assert (other / "precious.txt").read_text() == "keep me"


def test_writer_validates(tmp_path):
    meta = DatasetMeta(source="video", fps=25.0, image_size=(H, W), num_frames=0)
    with DatasetWriter(tmp_path / "a", meta) as w:
        with pytest.raises(ValueError, match="do not match"):
            w.add_frame(np.zeros((H + 1, W, 3)), np.zeros((H, W)), K=torch.eye(3), viewmat=torch.eye(4))
        w.add_frame(np.zeros((H, W, 3)), np.zeros((H, W)), K=torch.eye(3), viewmat=torch.eye(4))
        with pytest.raises(ValueError, match="regions must hold exactly"):
            w.add_frame(
                np.zeros((H, W, 3)),
                np.zeros((H, W)),
                K=torch.eye(3),
                viewmat=torch.eye(4),
                regions={"hand": np.zeros((H, W)), "face": np.zeros((H, W))},
            )
        with pytest.raises(ValueError, match="every frame or for none"):
            zeros = {r: np.zeros((H, W)) for r in ("hand_left", "hand_right", "face")}
            w.add_frame(
                np.zeros((H, W, 3)), np.zeros((H, W)), K=torch.eye(3), viewmat=torch.eye(4), regions=zeros
            )
        with pytest.raises(ValueError, match="outside"):
            w.finish({"train": [0, 1]})
        with pytest.raises(ValueError, match="unknown split"):
            w.finish({"validation": [0]})
    assert not (tmp_path / "a").exists()


def test_loader_rejects_broken_folders(tmp_path):
    with pytest.raises(DatasetError, match="no meta.json"):
        load_dataset(tmp_path)
    root, *_ = write_sample(tmp_path / "ds")
    meta = json.loads((root / "meta.json").read_text())
    (root / "meta.json").write_text(json.dumps({**meta, "format": "something-else"}))
    with pytest.raises(DatasetError, match="format"):
        load_dataset(root)
    (root / "meta.json").write_text(json.dumps({**meta, "num_frames": N + 1}))
    with pytest.raises(DatasetError, match="cameras"):
        load_dataset(root)
    (root / "meta.json").write_text(json.dumps(meta))
    (root / "frames" / "000002.png").unlink()
    ds = load_dataset(root)
    with pytest.raises(DatasetError, match="missing file"):
        ds.image(2)
    with pytest.raises(IndexError):
        ds.image(N)
    (root / "params.safetensors").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="body parameters"):
        load_dataset(root)
