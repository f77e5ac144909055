"""Retargeting: a motion fitted to one person drives an avatar of another.

Both are the same body model (the driving video is aligned with the avatar's own), so every
joint rotation and facial-expression coefficient carries over as it is; the avatar keeps its own
shape (``Avatar.subject_params`` puts it in). What changes is where the body is: a taller or
shorter avatar doing the same motion covers more or less ground, so the root's position is
scaled by the ratio of the two bodies' heights about a centre point. With the driving camera's
centre as that point, the avatar lands where the person was seen and, in that camera, covers them
(a perspective camera sees a scene scaled about its centre unchanged).
"""

from __future__ import annotations

import torch
from torch import Tensor

from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams


def _rest(body: BodyModel, shape: Tensor):
    params = body.default_params(1)
    params.shape = shape.to(params.shape).reshape(1, -1)
    with torch.no_grad():
        return body(params)


def body_height(body: BodyModel, shape: Tensor) -> float:
    """Height (metres) of ``body`` with ``shape [S]`` in its rest pose: the vertical extent of its
    vertices."""
    y = _rest(body, shape).vertices[0, :, 1]
    return float(y.max() - y.min())


def rest_root(body: BodyModel, shape: Tensor) -> Tensor:
    """[3] rest position of the root joint of ``body`` with ``shape [S]`` (root rotations turn
    about it; ``transl`` is added after)."""
    return _rest(body, shape).joints[0, 0].detach()


def retarget(
    source: BodyParams,
    body: BodyModel,
    target_shape: Tensor,
    center: Tensor | None = None,
    scale_translation: bool = True,
) -> BodyParams:
    """The motion ``source [T]`` (fitted to a person of shape ``source.shape``) for a subject of
    ``target_shape [S]``: joints, root orientation and expression as they are (expression clamped
    to the body model's valid range), shape replaced, and root positions scaled about
    ``center [3]`` (world, default the origin) by height(target) / height(source) when
    ``scale_translation`` (else the root joint follows the source's exactly). Returns [T].
    """
    t = source.batch_size
    target_shape = target_shape.detach().reshape(-1).to(source.shape)
    source_shape = source.shape.mean(0)  # a fit shares one shape over its frames
    ratio = body_height(body, target_shape) / body_height(body, source_shape) if scale_translation else 1.0
    center = torch.zeros(3) if center is None else torch.as_tensor(center)
    center = center.to(source.transl)
    # World position of the root joint per frame: rest root + transl (root_orient turns about it).
    same = torch.allclose(source.shape, source.shape[:1].expand_as(source.shape))
    shapes = source.shape[:1] if same else source.shape
    rests = torch.stack([rest_root(body, s) for s in shapes])  # [1 or T, 3]
    root_source = source.transl + rests.to(source.transl)
    root_target = center + ratio * (root_source - center)
    transl = root_target - rest_root(body, target_shape).to(source.transl)
    expression = source.expression
    if body.expression_bounds is not None:
        expression = expression.clamp(*body.expression_bounds)
    return BodyParams(
        root_orient=source.root_orient.clone(),
        transl=transl,
        joints=source.joints.clone(),
        expression=expression.clone(),
        shape=target_shape.expand(t, -1).clone(),
    )


def recenter(params: BodyParams, reference: int = 0) -> BodyParams:
    """``params [T]`` moved so that frame ``reference``'s root joint sits at its rest position
    (the origin of an orbit camera's default target): the motion's displacements stay."""
    shift = params.transl[reference].clone()
    return BodyParams(
        params.root_orient, params.transl - shift, params.joints, params.expression, params.shape
    )
