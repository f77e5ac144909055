"""SMPL-X backend on a generated SMPL-X-format file: the real loading code, agreement with the
smplx package's own forward, and clear errors when the user's files are missing."""

import pytest
import torch

from eva_engine.body import load_body_model
from eva_engine.body.smplx_backend import SMPLX_DIR_ENV


def random_params(model, batch=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = model.default_params(batch)
    p.joints.copy_(torch.randn(p.joints.shape, generator=g) * 0.5)
    p.root_orient.copy_(torch.randn(p.root_orient.shape, generator=g))
    p.transl.copy_(torch.randn(p.transl.shape, generator=g))
    p.shape.copy_(torch.randn(p.shape.shape, generator=g))
    p.expression.copy_(torch.randn(p.expression.shape, generator=g))
    return p


def test_with_pose_correctives_matches_the_smplx_package(smplx_dir):
    model = load_body_model("smplx", model_path=smplx_dir, pose_correctives=True)
    params = random_params(model)
    out = model(params)
    with torch.no_grad():
        ref = model.smplx(**model.smplx_inputs(params))
    assert (ref.vertices - out.vertices).abs().max() <= 1e-5
    assert (ref.joints[:, :55] - out.joints).abs().max() <= 1e-5
    # The correctives make a difference on this file, so the comparison above means something.
    plain = load_body_model("smplx", model_path=smplx_dir)
    assert (plain(params).vertices - out.vertices).abs().max() > 1e-4


def test_default_is_lbs_of_canonical_and_matches_smplx_without_correctives(smplx_model):
    params = random_params(smplx_model, seed=1)
    out = smplx_model(params)
    original = smplx_model.smplx.posedirs.clone()
    try:
        smplx_model.smplx.posedirs.zero_()
        with torch.no_grad():
            ref = smplx_model.smplx(**smplx_model.smplx_inputs(params))
    finally:
        smplx_model.smplx.posedirs.copy_(original)
    assert (ref.vertices - out.vertices).abs().max() <= 1e-5


def test_joint_and_parameter_names(smplx_model):
    assert smplx_model.joint_names[0] == "pelvis" and len(smplx_model.joint_names) == 55
    assert {"jaw", "left_eye_smplhf", "left_thumb3", "right_pinky1"} <= set(smplx_model.pose_joint_names)
    assert smplx_model.shape_names == [f"beta_{i}" for i in range(10)]
    assert smplx_model.expression_names == [f"expr_{i}" for i in range(10)]
    params = smplx_model.params_from_pose({"joints": {"left_elbow": [0, 0, 1]}, "shape": {"beta_0": 2.0}})
    assert params.joints[0, smplx_model.pose_joint_names.index("left_elbow"), 2] == 1.0


def test_env_var_locates_the_file(smplx_dir, monkeypatch):
    monkeypatch.setenv(SMPLX_DIR_ENV, str(smplx_dir))
    assert load_body_model("smplx").num_vertices == 10475
    monkeypatch.delenv(SMPLX_DIR_ENV)
    assert load_body_model("smplx", model_path=smplx_dir / "SMPLX_NEUTRAL.npz").num_joints == 55


def test_missing_files_name_the_setting(tmp_path, monkeypatch):
    monkeypatch.delenv(SMPLX_DIR_ENV, raising=False)
    with pytest.raises(FileNotFoundError, match=f"model_path.*{SMPLX_DIR_ENV}"):
        load_body_model("smplx")
    with pytest.raises(FileNotFoundError, match="SMPLX_NEUTRAL.npz"):
        load_body_model("smplx", model_path=tmp_path)
    monkeypatch.setenv(SMPLX_DIR_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match=SMPLX_DIR_ENV):
        load_body_model("smplx")


def test_unknown_backend_rejected():
    with pytest.raises(ValueError, match="anny"):
        load_body_model("smpl")
