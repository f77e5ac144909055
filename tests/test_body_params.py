"""BodyParams and the JSON pose form: round trip, defaults, and rejection of bad input."""

import json
import math

import pydantic
import pytest
import torch

from eva_engine.body import BodyParams, BodyPose, InvalidPoseError


def test_json_round_trip(anny_model):
    pose = BodyPose(
        joints={"lowerarm01.L": (0.0, 0.0, -1.25), "finger2-2.R": (0.5, 0.25, 0.0)},
        root_orient=(0.0, math.pi, 0.0),
        transl=(0.5, 0.0, -2.0),
        expression={"jawOpen": 0.75, "eyeBlinkLeft": 1.0},
        shape={"height": 0.25},
    )
    text = pose.model_dump_json()
    assert BodyPose.model_validate_json(text) == pose
    params = anny_model.params_from_pose(json.loads(text))
    assert params.batch_size == 1
    back = anny_model.pose_from_params(params)
    assert back.joints.keys() == pose.joints.keys()
    for name, value in pose.joints.items():
        assert back.joints[name] == pytest.approx(value, abs=1e-6)
    assert back.root_orient == pytest.approx(pose.root_orient, abs=1e-6)
    assert back.transl == pytest.approx(pose.transl)
    assert back.expression == pytest.approx(pose.expression)
    assert back.shape == pytest.approx(pose.shape)
    # The dense form carries every name and still round-trips.
    dense = anny_model.pose_from_params(params, sparse=False)
    assert len(dense.joints) == len(anny_model.pose_joint_names)
    assert torch.equal(anny_model.params_from_pose(dense).joints, params.joints)


def test_empty_pose_is_rest_pose_with_neutral_shape(anny_model):
    params = anny_model.params_from_pose({})
    rest = anny_model.default_params(1)
    for name, tensor in params.tensors().items():
        assert torch.equal(tensor, getattr(rest, name)), name
    assert params.shape.dtype == torch.float32
    assert torch.all(params.shape == 0.5)


def test_batch_of_poses(anny_model):
    params = anny_model.params_from_pose([{}, {"transl": [0, 1, 0]}, {"expression": {"jawOpen": 1}}])
    assert params.batch_size == 3
    assert params.transl[1, 1] == 1.0
    assert params[2].expression[0, anny_model.expression_names.index("jawOpen")] == 1.0
    assert BodyParams.cat([params[0], params[1:]]).batch_size == 3


@pytest.mark.parametrize(
    ("pose", "kind", "valid_example"),
    [
        ({"joints": {"elbow.L": [0, 0, 1]}}, "joint", "lowerarm01.L"),
        ({"joints": {"root": [0, 0, 1]}}, "joint", "pelvis.L"),  # the root is root_orient
        ({"expression": {"smile": 1.0}}, "expression", "mouthSmileLeft"),
        ({"shape": {"beta_0": 1.0}}, "shape", "proportions"),
    ],
)
def test_unknown_names_rejected_with_valid_list(anny_model, pose, kind, valid_example):
    with pytest.raises(InvalidPoseError) as err:
        anny_model.params_from_pose(pose)
    message = str(err.value)
    assert f"unknown {kind}" in message
    assert valid_example in message


@pytest.mark.parametrize(
    "raw",
    [
        '{"poses": {}}',  # unknown top-level key
        '{"transl": [0, 0]}',  # wrong length
        '{"root_orient": [0, 0, 0, 0]}',
        '{"joints": {"lowerarm01.L": [0, 0]}}',
        '{"joints": {"lowerarm01.L": [NaN, 0, 0]}}',
        '{"transl": [0, Infinity, 0]}',
        '{"expression": {"jawOpen": -Infinity}}',
        '{"shape": {"height": "tall"}}',
        '{"joints": []}',
    ],
)
def test_malformed_json_rejected(raw):
    with pytest.raises(pydantic.ValidationError):
        BodyPose.model_validate_json(raw)


def test_unknown_key_message_lists_valid_keys():
    with pytest.raises(pydantic.ValidationError, match="valid keys.*root_orient"):
        BodyPose.model_validate({"pose": {}})


def test_nan_rejected_from_python_values(anny_model):
    with pytest.raises(pydantic.ValidationError):
        anny_model.params_from_pose({"joints": {"lowerarm01.L": [float("nan"), 0.0, 0.0]}})
    with pytest.raises(pydantic.ValidationError):
        anny_model.params_from_pose({"expression": {"jawOpen": float("inf")}})


def test_json_schema_is_available_for_the_service():
    schema = BodyPose.model_json_schema()
    assert set(schema["properties"]) == {"joints", "root_orient", "transl", "expression", "shape"}
    assert schema.get("additionalProperties") is False


def test_body_params_checks_shapes():
    z = torch.zeros
    with pytest.raises(ValueError, match="joints"):
        BodyParams(z(2, 3), z(2, 3), z(2, 5), z(2, 4), z(2, 6))
    with pytest.raises(ValueError, match="transl"):
        BodyParams(z(2, 3), z(1, 3), z(2, 5, 3), z(2, 4), z(2, 6))
