"""``camera_from_spec``: the :class:`Camera` a ``CameraSpec`` (``eva_engine.specs.camera``) describes."""

from __future__ import annotations

import torch

from eva_engine.render.camera import Camera, intrinsics, orbit_camera
from eva_engine.specs.camera import DEFAULT_DISTANCE, DEFAULT_FOV_Y, CameraSpec


def camera_from_spec(spec: CameraSpec | None, width: int, height: int) -> Camera:
    """The camera ``spec`` describes, for a ``width`` x ``height`` image. Unset orbit values
    default to the front view (yaw 0, pitch 0) from ``DEFAULT_DISTANCE`` m at the world origin
    with ``DEFAULT_FOV_Y`` degrees."""
    spec = spec or CameraSpec()
    if spec.frame is not None:
        raise ValueError(
            "a training frame's camera needs the avatar's frames (avatar.render_spec.spec_camera)"
        )
    if spec.K is not None and spec.viewmat is not None:
        return Camera(torch.tensor(spec.K), torch.tensor(spec.viewmat), width, height)
    view = orbit_camera(
        spec.yaw or 0.0, spec.pitch or 0.0, spec.distance or DEFAULT_DISTANCE, spec.target or (0.0, 0.0, 0.0)
    )
    return Camera(intrinsics(width, height, spec.fov_y or DEFAULT_FOV_Y), view, width, height)
