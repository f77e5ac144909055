"""Differentiable 3D Gaussian rasterizer in torch, with compiled CPU kernels (CPU first, any device).

The functional core follows gsplat's conventions so a CUDA backend can be swapped in and compared:
``rasterize`` (project -> bin into tiles -> composite) returns a ``RenderOutput``. The stages are
public too: ``project_gaussians`` (EWA projection, autograd), ``bin_gaussians`` (no gradients),
``composite_image`` (tiled alpha compositing with a hand-written backward, compiled C++ kernels
or torch ones, see ``eva_engine.render.native``), ``composite`` (its torch kernels, tile layout)
and ``composite_autograd`` (the plain-autograd reference). Spherical-harmonics colours:
``eval_sh``. Cameras: ``Camera``, ``intrinsics``, ``look_at``, ``orbit_camera``.

``eva_engine.render.mesh`` is the other renderer: triangle meshes through OpenGL (``MeshRenderer``),
for ground-truth images and region masks, a deliberately different image formation model.
"""

from eva_engine.render.camera import Camera, intrinsics, look_at, orbit_camera
from eva_engine.render.composite import (
    CompositeConfig,
    composite,
    composite_autograd,
    composite_image,
    tiles_to_image,
)
from eva_engine.render.projection import Projection, project_gaussians, quat_to_rotmat
from eva_engine.render.rasterize import RASTERIZE_MODES, RasterConfig, RasterizeMode, RenderOutput, rasterize
from eva_engine.render.sh import eval_sh, num_sh_bases, rgb_to_sh, sh_basis, view_dirs
from eva_engine.render.tiles import TileBins, bin_gaussians

__all__ = [
    "Camera",
    "CompositeConfig",
    "Projection",
    "RASTERIZE_MODES",
    "RasterConfig",
    "RasterizeMode",
    "RenderOutput",
    "TileBins",
    "bin_gaussians",
    "composite",
    "composite_autograd",
    "composite_image",
    "eval_sh",
    "intrinsics",
    "look_at",
    "orbit_camera",
    "num_sh_bases",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
    "rgb_to_sh",
    "sh_basis",
    "tiles_to_image",
    "view_dirs",
]
