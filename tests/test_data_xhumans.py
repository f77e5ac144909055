"""XHumans reader on a tiny fake subject folder in the public layout (see data.xhumans)."""

from __future__ import annotations

import pickle
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from eva_engine.data import DatasetError, load_dataset
from eva_engine.data.xhumans import SMPLX_JOINT_NAMES, XHumansOptions, read_xhumans

H, W = 24, 16


def _smplx_frame(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "betas": rng.normal(size=(1, 10)).astype(np.float32),
        "global_orient": rng.normal(size=3).astype(np.float32),
        "body_pose": rng.normal(size=63).astype(np.float32),
        "left_hand_pose": rng.normal(size=45).astype(np.float32),
        "right_hand_pose": rng.normal(size=45).astype(np.float32),
        "jaw_pose": rng.normal(size=3).astype(np.float32),
        "leye_pose": np.zeros(3, np.float32),
        "reye_pose": np.zeros(3, np.float32),
        "expression": rng.normal(size=(1, 10)).astype(np.float32),
        "transl": rng.normal(size=3).astype(np.float32),
    }


def make_take(take: Path, n: int, rng: np.random.Generator, with_depth: bool = True) -> list[dict]:
    (take / "render" / "image").mkdir(parents=True)
    (take / "render" / "depth").mkdir(parents=True)
    (take / "SMPLX").mkdir(parents=True)
    frames = []
    extrinsic = np.tile(np.eye(4)[None, :3], (n, 1, 1))
    extrinsic[:, 2, 3] = np.arange(n) + 3.0
    np.savez(
        take / "render" / "cameras.npz",
        intrinsic=np.array([[20.0, 0, 8], [0, 20.0, 12], [0, 0, 1]]),
        extrinsic=extrinsic,
    )
    for k in range(1, n + 1):
        img = np.full((H, W, 3), 255, np.uint8)
        img[6:18, 4:12] = (200, 120, 90)
        img[0, 0] = (255, 255, 255)
        cv2.imwrite(str(take / "render" / "image" / f"color_{k:06d}.png"), img[..., ::-1])
        if with_depth:
            depth = np.full((H, W), 65535, np.uint16)
            depth[6:18, 4:12] = 3000
            cv2.imwrite(str(take / "render" / "depth" / f"depth_{k:06d}.tiff"), depth)
        d = _smplx_frame(rng)
        (take / "SMPLX" / f"mesh-f{k:05d}_smplx.pkl").write_bytes(pickle.dumps(d))
        frames.append(d)
    return frames


@pytest.fixture
def subject(tmp_path) -> tuple[Path, list[dict], list[dict]]:
    rng = np.random.default_rng(0)
    root = tmp_path / "00016"
    train = make_take(root / "train" / "Take1", 3, rng)
    test = make_take(root / "test" / "Take4", 12, rng, with_depth=False)
    (root / "gender.txt").write_text("female\n")
    return root, train, test


def test_reader_maps_layout_and_params(subject, tmp_path):
    root, train, test = subject
    out = read_xhumans(root, tmp_path / "ds", XHumansOptions(test_every=5, test_per_take=2))
    ds = load_dataset(out)
    assert ds.meta.source == "xhumans" and ds.meta.body_model == "smplx"
    assert ds.meta.extra["gender"] == "female"
    assert ds.splits["train"] == [0, 1, 2] and ds.splits["test_pose"] == [3, 4]
    assert ds.image_size == (H, W)
    # Test take sampled every 5th frame: files 1 and 6.
    assert ds.meta.extra["source_frames"][3:] == [
        "test/Take4/color_000001.png",
        "test/Take4/color_000006.png",
    ]
    assert ds.params is not None and ds.meta.params_source == "ground_truth"
    assert ds.param_names.joints == list(SMPLX_JOINT_NAMES[1:])
    p, src = ds.params, train + [test[0], test[5]]
    for i, d in enumerate(src):
        assert torch.allclose(p.root_orient[i], torch.from_numpy(d["global_orient"]))
        assert torch.allclose(p.joints[i, :21].reshape(-1), torch.from_numpy(d["body_pose"]))
        assert torch.allclose(p.joints[i, 21], torch.from_numpy(d["jaw_pose"]))
        assert torch.allclose(p.joints[i, 24:39].reshape(-1), torch.from_numpy(d["left_hand_pose"]))
        assert torch.allclose(p.joints[i, 39:].reshape(-1), torch.from_numpy(d["right_hand_pose"]))
        assert torch.allclose(p.shape[i], torch.from_numpy(d["betas"][0]))
        assert torch.allclose(p.expression[i], torch.from_numpy(d["expression"][0]))
        assert torch.allclose(p.transl[i], torch.from_numpy(d["transl"]))
    # Cameras: per-frame extrinsics, shared intrinsics.
    assert torch.allclose(ds.viewmat[:3, 2, 3], torch.tensor([3.0, 4.0, 5.0]))
    assert torch.allclose(ds.viewmat[4, 2, 3], torch.tensor(8.0))
    assert ds.K[0, 0, 0] == 20.0
    # Masks from depth (train) and from the background colour (test, no depth).
    for i in (0, 3):
        m = ds.mask(i)
        assert m[6:18, 4:12].min() == 1.0 and m.sum() == 12 * 8
    assert torch.allclose(ds.image(0)[10, 6], torch.tensor([200, 120, 90]) / 255.0)


def test_reader_resizes_and_scales_intrinsics(subject, tmp_path):
    root, _, _ = subject
    ds = load_dataset(read_xhumans(root, tmp_path / "ds", XHumansOptions(max_size=12)))
    assert ds.image_size == (12, 8)
    assert torch.allclose(ds.K[0], torch.tensor([[10.0, 0, 4], [0, 10.0, 6], [0, 0, 1]]))


def test_reader_refuses_unsafe_pickles_and_bad_folders(subject, tmp_path):
    root, _, _ = subject

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    (root / "train" / "Take1" / "SMPLX" / "mesh-f00002_smplx.pkl").write_bytes(
        pickle.dumps({"betas": Evil()})
    )
    with pytest.raises(DatasetError, match="refusing"):
        read_xhumans(root, tmp_path / "ds")
    assert not (tmp_path / "ds").exists()
    with pytest.raises(DatasetError, match="XHumans layout"):
        read_xhumans(tmp_path / "empty", tmp_path / "ds2")


def test_reader_writes_region_masks_with_the_users_smplx_model(tmp_path, smplx_model):
    """A subject in the rest pose seen from the front: each hand's mask on its own side of the
    image (the subject's left on the image's right), the face above both, all inside the person."""
    h, w = 96, 64
    take = tmp_path / "00001" / "train" / "Take1"
    for sub in ("render/image", "render/depth", "SMPLX"):
        (take / sub).mkdir(parents=True)
    view = np.diag([1.0, -1.0, -1.0])  # OpenCV camera on +Z looking at the origin, y down
    extrinsic = np.concatenate([view, [[0.0], [0.2], [3.0]]], axis=1)[None]
    intrinsic = np.array([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]])
    np.savez(take / "render" / "cameras.npz", intrinsic=intrinsic, extrinsic=extrinsic)
    cv2.imwrite(str(take / "render" / "image" / "color_000001.png"), np.full((h, w, 3), 128, np.uint8))
    cv2.imwrite(str(take / "render" / "depth" / "depth_000001.tiff"), np.full((h, w), 3000, np.uint16))
    rest = {k: np.zeros_like(v) for k, v in _smplx_frame(np.random.default_rng(0)).items()}
    (take / "SMPLX" / "mesh-f00001_smplx.pkl").write_bytes(pickle.dumps(rest))
    ds = load_dataset(read_xhumans(tmp_path / "00001", tmp_path / "ds", model=smplx_model))
    assert ds.has_region_masks
    f = ds[0]
    assert set(f.regions) == {"hand_left", "hand_right", "face"}
    centre = {}
    for name, m in f.regions.items():
        assert m.shape == (h, w) and float(m.sum()) > 1 and torch.all(m <= f.mask + 1 / 255)
        ys, xs = torch.nonzero(m > 0.5, as_tuple=True)
        centre[name] = (float(xs.float().mean()), float(ys.float().mean()))
    assert centre["hand_left"][0] > w / 2 > centre["hand_right"][0]
    assert centre["face"][1] < min(centre["hand_left"][1], centre["hand_right"][1])
    with pytest.raises(ValueError, match="SMPL-X"):
        read_xhumans(tmp_path / "00001", tmp_path / "ds2", model=SimpleNamespace(name="anny"))
