"""Pose controls: named sliders a person can move -- raise an arm, bend an elbow, curl a hand's
fingers, turn the head, open the jaw, smile -- each a rotation of some joints about anatomical
axes of *this* subject's rest skeleton (the elbow's hinge, the fingers' curl towards the palm),
or a weight on some facial actions. The web page builds its sliders from them and turns slider
values into the API's pose JSON:

- a joint's rotation is the product, in list order, of its controls' rotations
  ``exp(value * gain * axis)`` (as axis-angle in the ``BodyPose``);
- an expression coefficient is the sum of ``value * gain`` over its controls.

Only Anny's joint and expression names are described; a body model without them gets no
controls (``pose_controls`` returns those it can).
"""

from __future__ import annotations

import numpy as np
import torch
from pydantic import BaseModel, Field

from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams, BodyPose
from eva_engine.body.rest_axes import RestAxes, rest_axes

Vec3 = tuple[float, float, float]
_SKELETON = {
    f"{j}.{s}"
    for j in ("upperarm01", "lowerarm01", "wrist", "finger2-1", "finger3-1", "finger5-1")
    for s in "LR"
}


class JointTerm(BaseModel):
    joint: str
    axis: Vec3 = Field(description="Unit rotation axis in world axes of the rest pose.")
    gain: float = Field(1.0, description="Radians per unit of the control's value.")


class ExpressionTerm(BaseModel):
    expression: str
    gain: float = 1.0


class PoseControl(BaseModel):
    """One slider: ``value`` in [``min``, ``max``] (0: rest) moves ``joints`` and ``expressions``."""

    name: str
    label: str
    group: str
    min: float
    max: float
    value: float = 0.0
    joints: list[JointTerm] = Field(default_factory=list)
    expressions: list[ExpressionTerm] = Field(default_factory=list)


def _v(axis) -> Vec3:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    return (float(a[0]), float(a[1]), float(a[2]))


def _joint_controls(axes: RestAxes) -> list[PoseControl]:
    x, y, z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    minus_x = (-1.0, 0.0, 0.0)

    def split(axis: Vec3, lower: str, upper: str, low_gain: float) -> list[JointTerm]:
        """A rotation shared by two joints of a chain (neck and head, lower and upper spine)."""
        return [
            JointTerm(joint=lower, axis=axis, gain=low_gain),
            JointTerm(joint=upper, axis=axis, gain=1.0 - low_gain),
        ]

    head, torso = ("neck01", "head", 0.4), ("spine01", "spine03", 0.4)
    c: list[PoseControl] = [
        PoseControl(name="head_turn", label="Turn", group="Head", min=-1.2, max=1.2, joints=split(y, *head)),
        PoseControl(name="head_nod", label="Nod", group="Head", min=-0.8, max=0.8, joints=split(x, *head)),
        PoseControl(name="head_tilt", label="Tilt", group="Head", min=-0.6, max=0.6, joints=split(z, *head)),
        PoseControl(
            name="torso_bend", label="Bend forward", group="Torso", min=-0.4, max=0.8, joints=split(x, *torso)
        ),
        PoseControl(
            name="torso_twist", label="Twist", group="Torso", min=-0.8, max=0.8, joints=split(y, *torso)
        ),
    ]
    for s, side in (("L", "Left"), ("R", "Right")):
        sign = 1.0 if s == "L" else -1.0
        thumb = axes.finger[s][0]
        arm, hand, leg = f"{side} arm", f"{side} hand", f"{side} leg"
        curl = tuple(zip((1, 2, 3), (1.3, 1.5, 0.9), strict=True))  # per phalanx: bend more at the middle
        thumb_curl = tuple(zip((1, 2, 3), (0.5, 0.6, 0.5), strict=True))
        c += [
            PoseControl(
                name=f"arm_forward.{s}",
                label="Raise forward",
                group=arm,
                min=-0.6,
                max=2.6,
                joints=[JointTerm(joint=f"upperarm01.{s}", axis=minus_x)],
            ),
            PoseControl(
                name=f"arm_out.{s}",
                label="Raise sideways",
                group=arm,
                min=-0.8,
                max=1.8,
                joints=[JointTerm(joint=f"upperarm01.{s}", axis=(0.0, 0.0, sign))],
            ),
            PoseControl(
                name=f"elbow.{s}",
                label="Bend elbow",
                group=arm,
                min=0.0,
                max=2.4,
                joints=[JointTerm(joint=f"lowerarm01.{s}", axis=_v(axes.elbow[s]))],
            ),
            PoseControl(
                name=f"forearm_twist.{s}",
                label="Twist forearm",
                group=arm,
                min=-1.5,
                max=1.5,
                joints=[
                    JointTerm(joint=f"lowerarm02.{s}", axis=_v(axes.forearm[s]), gain=0.5),
                    JointTerm(joint=f"wrist.{s}", axis=_v(axes.forearm[s]), gain=0.5),
                ],
            ),
            PoseControl(
                name=f"wrist.{s}",
                label="Bend wrist",
                group=arm,
                min=-0.8,
                max=0.8,
                joints=[JointTerm(joint=f"wrist.{s}", axis=_v(axes.wrist_flex[s]))],
            ),
            PoseControl(
                name=f"fingers.{s}",
                label="Curl fingers",
                group=hand,
                min=0.0,
                max=1.0,
                joints=[
                    JointTerm(joint=f"finger{i}-{k}.{s}", axis=_v(axes.finger[s][i - 1]), gain=g)
                    for i in range(2, 6)
                    for k, g in curl
                ],
            ),
            PoseControl(
                name=f"thumb.{s}",
                label="Curl thumb",
                group=hand,
                min=0.0,
                max=1.0,
                joints=[JointTerm(joint=f"finger1-{k}.{s}", axis=_v(thumb), gain=g) for k, g in thumb_curl],
            ),
            PoseControl(
                name=f"hip.{s}",
                label="Raise leg",
                group=leg,
                min=-0.5,
                max=1.6,
                joints=[JointTerm(joint=f"upperleg01.{s}", axis=minus_x)],
            ),
            PoseControl(
                name=f"knee.{s}",
                label="Bend knee",
                group=leg,
                min=0.0,
                max=2.2,
                joints=[JointTerm(joint=f"lowerleg01.{s}", axis=x)],
            ),
        ]

    return c


def _face_controls() -> list[PoseControl]:
    def face(name: str, label: str, *names: str) -> PoseControl:
        return PoseControl(
            name=name,
            label=label,
            group="Face",
            min=0.0,
            max=1.0,
            expressions=[ExpressionTerm(expression=n) for n in names],
        )

    return [
        face("jaw_open", "Open jaw", "jawOpen"),
        face("smile", "Smile", "mouthSmileLeft", "mouthSmileRight"),
        face("brows_up", "Raise brows", "browInnerUp", "browOuterUpLeft", "browOuterUpRight"),
        face("brows_down", "Frown", "browDownLeft", "browDownRight"),
        face("blink", "Blink", "eyeBlinkLeft", "eyeBlinkRight"),
        face("pucker", "Pucker", "mouthPucker"),
    ]


def pose_controls(body: BodyModel, shape: torch.Tensor | None = None) -> list[PoseControl]:
    """The sliders for ``body`` with ``shape [S]`` (default neutral): those whose joints and
    expressions the model has (Anny: all of them)."""
    joints, expressions = set(body.pose_joint_names), set(body.expression_names)
    controls = []
    if _SKELETON <= joints:  # the rest-skeleton axes need Anny's arm and hand joints
        shape = body.shape_defaults if shape is None else shape
        controls = _joint_controls(rest_axes(body, shape.reshape(1, -1)))
    controls += _face_controls()

    def known(c: PoseControl) -> bool:
        return {t.joint for t in c.joints} <= joints and {t.expression for t in c.expressions} <= expressions

    return [c for c in controls if known(c)]


def pose_from_controls(controls: list[PoseControl], values: dict[str, float]) -> BodyPose:
    """The ``BodyPose`` for slider ``values`` (by control name; missing ones at 0), composed as
    the module docstring says (the web page does the same in JavaScript)."""
    from scipy.spatial.transform import Rotation

    unknown = set(values) - {c.name for c in controls}
    if unknown:
        raise ValueError(f"unknown control(s) {sorted(unknown)}")
    rotations: dict[str, Rotation] = {}
    expression: dict[str, float] = {}
    for control in controls:
        value = float(values.get(control.name, 0.0))
        if not control.min <= value <= control.max:
            raise ValueError(f"{control.name} = {value} is outside [{control.min}, {control.max}]")
        for term in control.joints:
            r = Rotation.from_rotvec(np.asarray(term.axis) * term.gain * value)
            rotations[term.joint] = rotations[term.joint] * r if term.joint in rotations else r
        for term in control.expressions:
            expression[term.expression] = expression.get(term.expression, 0.0) + term.gain * value
    joints = {name: tuple(float(v) for v in r.as_rotvec()) for name, r in rotations.items()}
    return BodyPose(
        joints={k: v for k, v in joints.items() if any(v)},  # type: ignore[arg-type]
        expression={k: v for k, v in expression.items() if v},
    )


def params_from_controls(
    body: BodyModel, controls: list[PoseControl], values: dict[str, float]
) -> BodyParams:
    """``pose_from_controls`` as ``BodyParams`` (batch 1) of ``body``."""
    return body.params_from_pose(pose_from_controls(controls, values))
