"""What an avatar saw in training, and how far a new pose or view lies outside it.

A Gaussian avatar is only constrained where training frames showed it: a view from a side the
video never showed, or a joint bent further than it ever was, renders surfaces nothing fitted.
:class:`Coverage` records the training range (``avatar.json`` keeps it) and
:meth:`Coverage.warnings` says, in words, what a render request asks for outside it.

- view: the camera's direction seen from the body, in the body's own frame (its root rotation
  undone), as yaw (degrees, positive towards the subject's left, 0 in front, as
  ``render.camera.orbit_camera``) and pitch (positive from above); the training range is the
  min and max over the frames;
- joints: per pose joint, the min and max of each axis-angle component over the frames;
- expression: per coefficient, the min and max over the frames.

A request is outside when a value lies beyond the range by more than a margin
(``CoverageMargins``).
"""

from __future__ import annotations

import math

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from eva_engine.body.kinematics import axis_angle_to_matrix
from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams
from eva_engine.geometry import camera_center


class CoverageMargins(BaseModel):
    """How far beyond the training range a request may go before it is warned about. On the
    novel-pose benchmark (``bench/results/novel_pose.md``, "Quality against novelty"), a camera
    10-20 deg beyond the training yaw range already doubles the full-image LPIPS-VGG of one inside
    it, and a pose whose worst joint is 40 deg or more from every training pose costs half as much
    again as the near test poses (15-30 deg): the angular margins sit just inside those."""

    model_config = ConfigDict(frozen=True)

    yaw_deg: float = 10.0
    pitch_deg: float = 10.0
    joint_rad: float = 0.35
    expression: float = 0.25


def rest_root(body: BodyModel, shape: Tensor) -> Tensor:
    """[3] the root joint's rest position of the subject with ``shape [1, S]``: where the body is
    in a frame is ``transl`` + this (the root turns about it)."""
    params = body.default_params(1)
    params.shape = shape.to(params.shape).reshape(1, -1)
    with torch.no_grad():
        return body(params).joints[0, 0]


def view_angles(params: BodyParams, viewmats: Tensor, root: Tensor) -> tuple[Tensor, Tensor]:
    """(yaw [F], pitch [F]) in degrees of each frame's camera seen from the body (module
    docstring). params: batch F; viewmats: [F, 4, 4] or [4, 4] world->camera; root: [3] the
    subject's rest root position (``rest_root``)."""
    dtype = torch.float64
    n = params.batch_size
    viewmats = viewmats.to(dtype=dtype, device=params.transl.device)
    viewmats = viewmats.expand(n, 4, 4) if viewmats.ndim == 2 else viewmats
    position = params.transl.detach().to(dtype) + root.to(params.transl.device, dtype)  # [F, 3]
    rot = axis_angle_to_matrix(params.root_orient.detach().to(dtype))  # [F, 3, 3] body -> world
    d = (rot.transpose(-1, -2) @ (camera_center(viewmats) - position)[..., None])[..., 0]
    yaw = torch.rad2deg(torch.atan2(d[:, 0], d[:, 2]))
    pitch = torch.rad2deg(torch.atan2(d[:, 1], torch.hypot(d[:, 0], d[:, 2])))
    return yaw, pitch


def rotation_distance(a: Tensor, b: Tensor) -> Tensor:
    """Geodesic angle (radians) between axis-angle rotations a [..., 3] and b [..., 3]."""
    rel = axis_angle_to_matrix(a).transpose(-1, -2) @ axis_angle_to_matrix(b)
    cos = ((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.acos(cos)


def nearest_pose_distance(
    test: Tensor, train: Tensor, joints: Tensor | None = None, chunk: int = 64
) -> tuple[Tensor, Tensor]:
    """For every test pose, the training pose whose worst joint is closest to it.

    test: [T, P, 3], train: [F, P, 3] axis-angles; joints: [P] bool, the joints to compare (None:
    all). Returns (distance [T] in radians: the largest geodesic joint angle to that training
    pose, index [T] of the training pose)."""
    if joints is not None:
        test, train = test[:, joints], train[:, joints]
    dists, idx = [], []
    for start in range(0, test.shape[0], chunk):
        t = test[start : start + chunk]
        d = rotation_distance(t[:, None], train[None]).amax(dim=-1)  # [t, F]
        best = d.min(dim=1)
        dists.append(best.values)
        idx.append(best.indices)
    return torch.cat(dists), torch.cat(idx)


class Range(BaseModel):
    model_config = ConfigDict(frozen=True)

    min: float
    max: float

    def excess(self, value: float) -> float:
        """How far ``value`` lies outside [min, max] (0 inside)."""
        return max(self.min - value, value - self.max, 0.0)


class Coverage(BaseModel):
    """The training range of an avatar (module docstring); ``avatar.json``'s ``coverage``."""

    model_config = ConfigDict(extra="forbid")

    frames: int
    root: tuple[float, float, float]
    """The subject's rest root position (``rest_root``), metres."""
    yaw_deg: Range
    pitch_deg: Range
    joints: dict[str, tuple[Range, Range, Range]] = Field(default_factory=dict)
    expression: dict[str, Range] = Field(default_factory=dict)

    @classmethod
    def of_frames(cls, body: BodyModel, params: BodyParams, viewmats: Tensor) -> Coverage:
        """The coverage of training frames: ``params`` (batch F) seen through ``viewmats``
        [F, 4, 4]."""
        if params.batch_size == 0:
            raise ValueError("no training frames to take a coverage of")
        root = rest_root(body, params.shape[:1].detach())
        yaw, pitch = view_angles(params, viewmats, root)
        joints = params.joints.detach().double()
        lo, hi = joints.amin(dim=0), joints.amax(dim=0)  # [P, 3]
        expr = params.expression.detach().double()
        return cls(
            frames=params.batch_size,
            root=tuple(float(x) for x in root),
            yaw_deg=Range(min=float(yaw.min()), max=float(yaw.max())),
            pitch_deg=Range(min=float(pitch.min()), max=float(pitch.max())),
            joints={
                name: tuple(Range(min=float(lo[j, k]), max=float(hi[j, k])) for k in range(3))
                for j, name in enumerate(body.pose_joint_names)
            },
            expression={
                name: Range(min=float(expr[:, e].min()), max=float(expr[:, e].max()))
                for e, name in enumerate(body.expression_names)
            },
        )

    def warnings(
        self,
        body: BodyModel,
        params: BodyParams,
        viewmat: Tensor,
        margins: CoverageMargins | None = None,
    ) -> list[str]:
        """What a render of ``params`` (batch 1) through ``viewmat`` [4, 4] asks for beyond the
        training range, one sentence each (empty: all inside). ``body`` names the joints and
        expressions (no forward pass: a render pays only a few small comparisons)."""
        m = margins or CoverageMargins()
        out = []
        yaw, pitch = (float(a[0]) for a in view_angles(params, viewmat, torch.tensor(self.root)))
        for what, value, rng, margin, sides in (
            ("yaw", yaw, self.yaw_deg, m.yaw_deg, ("to the subject's right", "to the subject's left")),
            ("pitch", pitch, self.pitch_deg, m.pitch_deg, ("from below", "from above")),
        ):
            if rng.excess(value) > margin:
                side = sides[0] if value < rng.min else sides[1]
                out.append(
                    f"the camera is at {what} {value:.0f} deg ({side}); training saw "
                    f"{rng.min:.0f} to {rng.max:.0f} deg: surfaces there were never fitted"
                )
        joints = params.joints[0].detach().double().tolist()  # [P][3] floats: one copy, not P
        outside = []
        for name, values in zip(body.pose_joint_names, joints, strict=True):
            ranges = self.joints.get(name)
            if ranges is None:
                continue
            excess = max(r.excess(v) for r, v in zip(ranges, values, strict=True))
            if excess > m.joint_rad:
                outside.append((excess, name))
        if outside:
            outside.sort(reverse=True)
            names = ", ".join(f"{n} ({math.degrees(e):.0f} deg)" for e, n in outside[:6])
            more = f" and {len(outside) - 6} more" if len(outside) > 6 else ""
            out.append(f"joints bent beyond what training showed: {names}{more}")
        expr = params.expression[0].detach().double().tolist()
        beyond = [
            name
            for name, value in zip(body.expression_names, expr, strict=True)
            if name in self.expression and self.expression[name].excess(value) > m.expression
        ]
        if beyond:
            more = f" and {len(beyond) - 6} more" if len(beyond) > 6 else ""
            out.append(f"facial actions beyond what training showed: {', '.join(beyond[:6])}{more}")
        return out
