"""Avatar files: PLY round trip through plyfile, save/reload gives identical renders, clear errors."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest
import torch
from helpers.scenes import front_camera, random_params
from plyfile import PlyData
from pydantic import ValidationError

from eva_engine.avatar import (
    Avatar,
    AvatarConfig,
    AvatarFileError,
    AvatarFrames,
    FramesInfo,
    TrainingRecord,
    load_avatar,
    load_avatar_frames,
    load_saved_avatar,
    read_avatar_meta,
    read_ply,
    save_avatar,
    write_ply,
)


@pytest.fixture(scope="module")
def trained_like(anny_model):
    """An avatar whose every learnable part differs from its initial value."""
    torch.manual_seed(0)
    cfg = AvatarConfig(init_max_gaussians=500, mlp_width=16, pe_frequencies=2, sh_degree=2)
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, cfg)
    with torch.no_grad():
        for p in avatar.gaussians.splats.values():
            p.add_(0.05 * torch.randn_like(p))
        for p in avatar.mlp_parameters():
            p.add_(0.02 * torch.randn_like(p))
        avatar.gaussians.part_ids[:7] = 1
    avatar.active_sh_degree = 2
    return avatar


def test_ply_round_trip_standard_layout(tmp_path, trained_like):
    splats = dict(trained_like.gaussians.splats.items())
    path = tmp_path / "a.ply"
    write_ply(path, splats)
    names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    k = (2 + 1) ** 2 - 1
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(3 * k)] + ["opacity"]
    expected += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    assert names == expected
    back = read_ply(path)
    for name, value in splats.items():
        assert torch.equal(back[name], value.detach()), name
    # 3DGS stores f_rest channel-major: f_rest_0..k-1 are the red coefficients.
    v = PlyData.read(str(path))["vertex"]
    np.testing.assert_array_equal(v["f_rest_1"], splats["shN"][:, 1, 0].detach().numpy())
    np.testing.assert_array_equal(v[f"f_rest_{k}"], splats["shN"][:, 0, 1].detach().numpy())


def test_ply_round_trip_of_sh_degree_zero(tmp_path, anny_model):
    """Base colours only: no f_rest columns in the file, and it reads back."""
    config = AvatarConfig(init_max_gaussians=200, sh_degree=0)
    avatar = Avatar.create(anny_model, anny_model.shape_defaults, config)
    write_ply(tmp_path / "dc.ply", dict(avatar.gaussians.splats.items()))
    back = read_ply(tmp_path / "dc.ply")
    assert back["shN"].shape == (len(avatar.gaussians), 0, 3)
    assert torch.equal(back["sh0"], avatar.gaussians.splats["sh0"].detach())


def test_save_reload_renders_identically(tmp_path, anny_model, trained_like):
    record = TrainingRecord(train_seconds=1.5, metrics={"psnr": 30.0})
    out = save_avatar(trained_like, tmp_path / "av", record)
    assert sorted(p.name for p in out.iterdir()) == ["avatar.json", "avatar.ply", "avatar.safetensors"]
    doc = json.loads((out / "avatar.json").read_text())
    assert doc["num_gaussians"] == len(trained_like.gaussians) and doc["body_model"] == "anny"
    assert doc["train_seconds"] == 1.5 and doc["avatar_config"]["sh_degree"] == 2
    assert b"pickle" not in (out / "avatar.safetensors").read_bytes()[:64]
    back = load_avatar(out, body=anny_model)
    assert torch.equal(back.gaussians.part_ids, trained_like.gaussians.part_ids)
    assert back.active_sh_degree == 2
    cam = front_camera(40)
    for seed in (1, 2):
        params = random_params(anny_model, 1, seed)
        assert torch.equal(back.render(params, cam), trained_like.render(params, cam))


def test_load_errors_are_clear(tmp_path, anny_model, trained_like):
    with pytest.raises(AvatarFileError, match="no avatar directory"):
        load_avatar(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(AvatarFileError, match="avatar.json"):
        load_avatar(tmp_path / "empty")
    out = save_avatar(trained_like, tmp_path / "av")
    (out / "avatar.ply").unlink()
    with pytest.raises(AvatarFileError, match="incomplete"):
        load_avatar(out, body=anny_model)
    (out / "avatar.json").write_text("{not json")
    with pytest.raises(AvatarFileError, match="JSON"):
        load_avatar(out, body=anny_model)


def test_the_whole_directory_round_trips(tmp_path, anny_model, trained_like):
    """Gaussians, avatar.json (typed) and the training frames: written once, read back as one."""
    frames = AvatarFrames(
        params=random_params(anny_model, 3, seed=4),
        K=front_camera(40).K.expand(3, 3, 3),
        viewmat=front_camera(40).viewmat.expand(3, 4, 4),
        timestamps=torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64),
        image_size=(48, 40),
        fps=2.0,
    )
    record = TrainingRecord(preset="tiny", method="eva", iterations=30, metrics={"psnr": 31.5})
    out = save_avatar(trained_like, tmp_path / "av", record, frames=frames)
    saved = load_saved_avatar(out, body=anny_model)
    assert saved.meta.preset == "tiny" and saved.meta.method == "eva" and saved.meta.iterations == 30
    assert saved.meta.num_gaussians == len(trained_like.gaussians) and saved.meta.metrics == {"psnr": 31.5}
    assert saved.meta.frames == FramesInfo(count=3, image_size=(48, 40), fps=2.0)
    assert saved.frames is not None and len(saved.frames) == 3 and saved.frames.image_size == (48, 40)
    for name, value in frames.params.tensors().items():
        assert torch.equal(getattr(saved.frames.params, name), value.float()), name
    assert torch.equal(saved.frames.K, frames.K) and torch.equal(saved.frames.timestamps, frames.timestamps)
    # Saved again without frames: none are left behind.
    save_avatar(trained_like, out)
    assert load_avatar_frames(out) is None and read_avatar_meta(out).frames is None
    with pytest.raises(ValidationError):
        TrainingRecord(train_secs=1.0)  # a typo is an error, not a silent extra key


def test_reads_avatar_json_as_earlier_versions_wrote_it(tmp_path, anny_model, trained_like):
    """The writers before the typed artefact: a free-form dict (nulls for unknowns, keys this
    reader does not know, no active SH degree)."""
    out = save_avatar(trained_like, tmp_path / "av")
    old = {
        "format": "eva-avatar",
        "version": 1,
        "body_model": "anny",
        "num_gaussians": len(trained_like.gaussians),
        "avatar_config": json.loads((out / "avatar.json").read_text())["avatar_config"],
        "preset": "fast",
        "method": None,
        "train_seconds": 12.5,
        "iterations": 600,
        "final_loss": 0.05,
        "metrics": {"split": "train", "psnr": 28.0},
        "frames": {"count": 4, "image_size": [96, 64], "fps": 25.0},
        "some_later_field": {"kept": False},
    }
    (out / "avatar.json").write_text(json.dumps(old))
    meta = read_avatar_meta(out)
    assert meta.preset == "fast" and meta.method is None and meta.train_seconds == 12.5
    assert meta.frames == FramesInfo(count=4, image_size=(96, 64), fps=25.0)
    assert load_avatar(out, body=anny_model).active_sh_degree == trained_like.gaussians.sh_degree


def test_expression_frames_survive_saving_and_old_avatars_keep_offsets(tmp_path, anny_model, trained_like):
    """An avatar trained with the skin's frames renders with them after a reload; one saved
    before the setting existed (no such key) renders as it was trained: vertex offsets only."""
    framed = copy.deepcopy(trained_like)
    framed.config = dataclasses.replace(framed.config, expression_frames=True)
    out = save_avatar(framed, tmp_path / "framed")
    assert load_avatar(out, body=anny_model).config.expression_frames
    doc = json.loads((out / "avatar.json").read_text())
    del doc["avatar_config"]["expression_frames"]
    (out / "avatar.json").write_text(json.dumps(doc))
    old = load_avatar(out, body=anny_model)
    assert not old.config.expression_frames
    params = anny_model.params_from_pose({"expression": {"jawOpen": 0.8, "eyeBlinkLeft": 1.0}})
    cam = front_camera(40)
    assert torch.equal(old.render(params, cam), trained_like.render(params, cam))
