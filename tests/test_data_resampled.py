"""``ResampledDataset``: frames, masks and intrinsics at another resolution, consistent with each
other; training with ``image_scale`` sees exactly this view."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from helpers.scenes import teacher_scene

from eva_engine.data import DatasetLike, ResampledDataset, resample_frame
from eva_engine.train import preset, train_avatar


@pytest.fixture(scope="module")
def scene(anny_model):
    return teacher_scene(anny_model, n_frames=4, size=64)


def test_a_frame_at_half_size(scene):
    ds, _ = scene
    view: DatasetLike = ResampledDataset(ds, 0.5)
    frame, half = ds[1], view[1]
    assert half.image.shape == (32, 32, 3) and half.mask.shape == (32, 32)
    assert view.meta.image_size == (32, 32) and ds.meta.image_size == (64, 64)
    assert set(half.regions) == set(frame.regions) and all(m.shape == (32, 32) for m in half.regions.values())
    # Area averaging: every 2x2 block becomes its mean.
    blocks = frame.image.reshape(32, 2, 32, 2, 3).mean(dim=(1, 3))
    assert torch.allclose(half.image, blocks, atol=1e-6)
    # The intrinsics follow: a point lands on the same place of the picture (pixel corners at 0).
    point = torch.tensor([0.1, 0.3, 0.05, 1.0])
    cam = frame.viewmat @ point

    def pixel(K: torch.Tensor) -> torch.Tensor:
        uv = K @ cam[:3]
        return uv[:2] / uv[2]

    assert torch.allclose(pixel(half.K), pixel(frame.K) * 0.5, atol=1e-5)
    assert torch.equal(half.viewmat, frame.viewmat) and half.index == frame.index
    assert view.splits is ds.splits and view.params is ds.params and len(view) == len(ds)


def test_odd_sizes_round_and_scale_one_is_the_frame(scene):
    ds, _ = scene
    frame = ds[0]
    odd = resample_frame(frame, 0.3)  # 64 * 0.3 = 19.2 -> 19
    assert odd.image.shape[:2] == (19, 19)
    assert odd.K[0, 0] == pytest.approx(float(frame.K[0, 0]) * 19 / 64)
    assert resample_frame(frame, 1.0) is frame
    with pytest.raises(ValueError, match="scale"):
        ResampledDataset(ds, 0.0)


def test_training_with_an_image_scale_trains_on_the_view(scene, anny_model):
    ds, _ = scene
    cfg = preset("tiny", iterations=4)
    cfg = dataclasses.replace(cfg, loss=dataclasses.replace(cfg.loss, lambda_lpips=0.0))
    scaled = train_avatar(ds, dataclasses.replace(cfg, image_scale=0.5), body=anny_model)
    viewed = train_avatar(ResampledDataset(ds, 0.5), cfg, body=anny_model)
    assert scaled.losses == viewed.losses
    assert torch.equal(scaled.avatar.gaussians.means, viewed.avatar.gaussians.means)
