"""Body parameters: the batched tensor form (:class:`BodyParams`) and the JSON form of one pose
(:class:`BodyPose`), which the render endpoint accepts as its schema.

Conventions (the project's world frame: Y up, the subject faces +Z, metres):

- ``root_orient [B, 3]``: axis-angle of the root joint about its rest position, world axes.
- ``transl [B, 3]``: world translation in metres added after the root rotation.
- ``joints [B, P, 3]``: axis-angle of every other joint (``model.pose_joint_names``, the
  ``model.joint_names`` without the root) relative to its parent, expressed in world-aligned axes
  of the rest pose (as in SMPL-X), so ``[0, 0, 0]`` everywhere is the rest pose.
- ``expression [B, E]``: ``model.expression_names`` coefficients (Anny: ARKit-52 in [0, 1]).
- ``shape [B, S]``: ``model.shape_names`` coefficients (Anny: phenotypes in [0, 1], 0.5 neutral).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

Vec3 = tuple[float, float, float]


class InvalidPoseError(ValueError):
    """A pose names a joint, expression or shape parameter the body model does not have."""


class BodyPose(BaseModel):
    """One pose as JSON: every key optional; unspecified joints stay at rest, unspecified
    expression coefficients at 0 and unspecified shape parameters at the model's neutral values.

    ``{"joints": {name: [rx, ry, rz]}, "root_orient": [3], "transl": [3],
    "expression": {name: value}, "shape": {name: value}}``
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

    joints: dict[str, Vec3] = Field(
        default_factory=dict, description="Axis-angle [rx, ry, rz] (radians) per joint name."
    )
    root_orient: Vec3 = Field((0.0, 0.0, 0.0), description="Root axis-angle (radians), world axes.")
    transl: Vec3 = Field((0.0, 0.0, 0.0), description="Root translation in metres, world axes.")
    expression: dict[str, float] = Field(
        default_factory=dict, description="Facial expression coefficient per name."
    )
    shape: dict[str, float] = Field(default_factory=dict, description="Shape parameter per name.")

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data):
        # pydantic's own "extra forbidden" error does not say what is allowed.
        if isinstance(data, dict):
            unknown = [k for k in data if k not in cls.model_fields]
            if unknown:
                raise ValueError(f"unknown key(s) {unknown}; valid keys: {list(cls.model_fields)}")
        return data


@dataclasses.dataclass
class BodyParams:
    """Batched body parameters (float tensors on one device), see the module docstring.

    root_orient: [B, 3], transl: [B, 3], joints: [B, P, 3], expression: [B, E], shape: [B, S].
    """

    root_orient: torch.Tensor
    transl: torch.Tensor
    joints: torch.Tensor
    expression: torch.Tensor
    shape: torch.Tensor

    def __post_init__(self) -> None:
        b = self.root_orient.shape[0]
        checks = {
            "root_orient": (self.root_orient, 2, 3),
            "transl": (self.transl, 2, 3),
            "joints": (self.joints, 3, 3),
            "expression": (self.expression, 2, None),
            "shape": (self.shape, 2, None),
        }
        for name, (t, ndim, last) in checks.items():
            if t.ndim != ndim or t.shape[0] != b or (last is not None and t.shape[-1] != last):
                raise ValueError(
                    f"BodyParams.{name} has shape {tuple(t.shape)}; expected {ndim} dims, "
                    f"batch {b}" + (f", last dim {last}" if last else "")
                )

    @property
    def batch_size(self) -> int:
        return self.root_orient.shape[0]

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def map(self, fn) -> BodyParams:
        """A new ``BodyParams`` with ``fn`` applied to every tensor (``.to``, ``.detach``, slicing)."""
        return BodyParams(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, *args, **kwargs) -> BodyParams:
        return self.map(lambda t: t.to(*args, **kwargs))

    def detach(self) -> BodyParams:
        return self.map(lambda t: t.detach())

    def __getitem__(self, index) -> BodyParams:
        """Select frames, keeping the batch dimension (an int index gives a batch of one)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return self.map(lambda t: t[index])

    @staticmethod
    def cat(items: Sequence[BodyParams]) -> BodyParams:
        return BodyParams(
            **{f.name: torch.cat([getattr(p, f.name) for p in items]) for f in dataclasses.fields(BodyParams)}
        )


def _check_names(kind: str, given: Sequence[str], valid: Sequence[str]) -> None:
    unknown = [n for n in given if n not in set(valid)]
    if unknown:
        raise InvalidPoseError(f"unknown {kind} name(s) {unknown}; valid names: {list(valid)}")


def params_from_poses(
    poses: Sequence[BodyPose | dict],
    *,
    pose_joint_names: Sequence[str],
    expression_names: Sequence[str],
    shape_names: Sequence[str],
    shape_defaults: torch.Tensor,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> BodyParams:
    """Batch of JSON poses -> :class:`BodyParams` ``[len(poses), ...]``.

    Raises ``pydantic.ValidationError`` for malformed values (wrong lengths, NaN/Inf, unknown
    keys) and :class:`InvalidPoseError` for names the model does not have.
    """
    if len(poses) == 0:
        raise ValueError("need at least one pose")
    poses = [p if isinstance(p, BodyPose) else BodyPose.model_validate(p) for p in poses]
    joint_index = {n: i for i, n in enumerate(pose_joint_names)}
    expr_index = {n: i for i, n in enumerate(expression_names)}
    shape_index = {n: i for i, n in enumerate(shape_names)}
    b = len(poses)
    root = torch.zeros(b, 3, dtype=torch.float64)
    transl = torch.zeros(b, 3, dtype=torch.float64)
    joints = torch.zeros(b, len(pose_joint_names), 3, dtype=torch.float64)
    expression = torch.zeros(b, len(expression_names), dtype=torch.float64)
    shape = shape_defaults.detach().to("cpu", torch.float64).expand(b, -1).clone()
    for i, pose in enumerate(poses):
        _check_names("joint", list(pose.joints), pose_joint_names)
        _check_names("expression", list(pose.expression), expression_names)
        _check_names("shape", list(pose.shape), shape_names)
        root[i] = torch.tensor(pose.root_orient, dtype=torch.float64)
        transl[i] = torch.tensor(pose.transl, dtype=torch.float64)
        for name, value in pose.joints.items():
            joints[i, joint_index[name]] = torch.tensor(value, dtype=torch.float64)
        for name, value in pose.expression.items():
            expression[i, expr_index[name]] = value
        for name, value in pose.shape.items():
            shape[i, shape_index[name]] = value
    params = BodyParams(root, transl, joints, expression, shape)
    return params.to(device=device, dtype=dtype)


def pose_from_params(
    params: BodyParams,
    index: int = 0,
    *,
    pose_joint_names: Sequence[str],
    expression_names: Sequence[str],
    shape_names: Sequence[str],
    shape_defaults: torch.Tensor | None = None,
    sparse: bool = True,
) -> BodyPose:
    """Frame ``index`` of ``params`` -> :class:`BodyPose`. With ``sparse``, joints at rest,
    zero expression coefficients and shape values at their defaults are left out."""
    p = params[index].detach().to("cpu", torch.float64)

    def vec(t: torch.Tensor) -> Vec3:
        return tuple(float(x) for x in t)  # type: ignore[return-value]

    joints = {n: vec(p.joints[0, i]) for i, n in enumerate(pose_joint_names)}
    expression = {n: float(p.expression[0, i]) for i, n in enumerate(expression_names)}
    shape = {n: float(p.shape[0, i]) for i, n in enumerate(shape_names)}
    if sparse:
        joints = {n: v for n, v in joints.items() if any(x != 0.0 for x in v)}
        expression = {n: v for n, v in expression.items() if v != 0.0}
        if shape_defaults is not None:
            defaults = [float(x) for x in shape_defaults.detach().cpu().double()]
            shape = {
                n: v for (n, v), d in zip(shape.items(), defaults, strict=True) if not math.isclose(v, d)
            }
    return BodyPose(
        joints=joints,
        root_orient=vec(p.root_orient[0]),
        transl=vec(p.transl[0]),
        expression=expression,
        shape=shape,
    )
