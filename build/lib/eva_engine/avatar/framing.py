"""Where to point an orbit camera so an avatar fills the picture: an avatar trained on a waist-up
video has Gaussians only above the waist (parts never seen get none), so the world origin and a
full-body distance would show it small and high. ``framing`` measures the avatar's Gaussians in
its rest pose instead."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from eva_engine.avatar.model import Avatar
from eva_engine.specs.camera import CameraSpec


@dataclass(frozen=True)
class Framing:
    """An orbit camera's ``target`` (world, metres), ``distance`` (metres) and vertical field of
    view ``fov_y`` (degrees) that fit the avatar, as ``CameraSpec`` fields."""

    target: tuple[float, float, float]
    distance: float
    fov_y: float

    def camera(self, yaw: float = 0.0, pitch: float = 0.0) -> dict:
        """A ``CameraSpec`` dict for this framing seen from ``yaw``, ``pitch`` (degrees)."""
        return {
            "yaw": yaw,
            "pitch": pitch,
            "target": list(self.target),
            "distance": self.distance,
            "fov_y": self.fov_y,
        }


def framing(avatar: Avatar, fov_y: float = 35.0, aspect: float = 1.0, margin: float = 0.25) -> Framing:
    """Fit the avatar's visible Gaussians in the rest pose (1st-99th percentile box of the centres
    of Gaussians with opacity > 0.2) into a view of ``fov_y`` degrees and width/height ``aspect``
    from any yaw, with ``margin`` (a fraction of the box) around it for limbs that move out of it.
    """
    g = avatar.gaussians
    with torch.no_grad():
        means = g.means.detach().float()
        visible = g.opacities().detach().reshape(-1) > 0.2
        points = means[visible] if int(visible.sum()) >= 10 else means
    if points.shape[0] == 0:  # no Gaussians at all: the body model's rest pose from the front
        return Framing((0.0, 0.0, 0.0), 2.6, fov_y)
    lo = torch.quantile(points, 0.01, dim=0)
    hi = torch.quantile(points, 0.99, dim=0)
    center = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo) * (1.0 + margin)
    half_height = float(half[1])
    half_width = float(torch.maximum(half[0], half[2]))  # the widest side seen from any yaw
    tan_y = math.tan(math.radians(fov_y) / 2)
    # Far enough that the box's near face (half_width in front of the target) fits the view.
    distance = max(half_height / tan_y, half_width / (tan_y * aspect)) + half_width
    return Framing(tuple(float(x) for x in center), max(distance, 0.3), fov_y)  # type: ignore[arg-type]


def framed_camera(avatar: Avatar, spec: CameraSpec | None, width: int, height: int) -> CameraSpec:
    """``spec`` with what an orbit leaves unset -- ``target``, ``distance``, ``fov_y`` -- filled by
    :func:`framing` for a ``width`` x ``height`` image (a K/viewmat camera is returned as it is)."""
    spec = spec or CameraSpec()
    if not spec.is_orbit or (spec.target is not None and spec.distance is not None):
        return spec
    fit = framing(avatar, fov_y=spec.fov_y or 35.0, aspect=width / height)
    return CameraSpec.model_validate({**fit.camera(), **spec.model_dump(exclude_none=True)})
