"""The demo's engine side: the new pose it asks the avatar for, a synthetic signer video, and a
quick body-only scene.

``eva demo`` runs the whole product (``service.demo``): ``signer_video`` writes a video of a
synthetic signer (the Anny body rendered as a textured mesh), the service turns it into an
avatar, and the avatar is rendered in ``DEMO_POSE`` (a wave, curled fingers, a smile).
``render_demo`` (``eva demo --body-only``) renders the posed body model as surface Gaussians
with ``eva_engine.render`` -- the body model and rasterizer alone, in a second.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from eva_engine.body import BodyModel
from eva_engine.geometry import quat_from_z, vertex_normals
from eva_engine.render import intrinsics, orbit_camera, rasterize

# Part colours (body, hand, face): distinct, so a wrong part id is visible at a glance.
PART_COLORS = ((0.25, 0.45, 0.85), (0.95, 0.55, 0.2), (0.9, 0.75, 0.65))
DEMO_POSE = {
    "joints": {
        "upperarm01.R": [0.0, 0.0, -1.5],
        "lowerarm01.R": [0.0, 0.0, -0.9],
        "upperarm01.L": [0.0, 0.3, -1.0],
        "lowerarm01.L": [0.0, -1.0, 0.0],
        "finger2-1.L": [0.0, 0.0, 0.9],
        "finger3-1.L": [0.0, 0.0, 1.1],
        "neck01": [0.1, 0.2, 0.0],
    },
    "expression": {"mouthSmileLeft": 0.8, "mouthSmileRight": 0.8, "jawOpen": 0.3},
}


@dataclass
class SurfaceGaussians:
    """Flat Gaussians (surfels) on a triangle mesh, one per vertex.

    means: [N, 3]; quats: [N, 4] (w, x, y, z) turning +z onto the vertex normal;
    scales: [N, 3] (tangent, tangent, normal) standard deviations; normals: [N, 3] unit.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    normals: Tensor


def surface_gaussians(vertices: Tensor, faces: Tensor, thickness: float = 0.15) -> SurfaceGaussians:
    """Surfels on a mesh: tangent extent = 0.4 x the longest edge at a vertex (closes the gaps
    of long, thin quads on limbs)."""
    edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lengths = (vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=-1)
    longest = torch.zeros(len(vertices), dtype=vertices.dtype).scatter_reduce_(
        0, edges.reshape(-1), lengths.repeat_interleave(2), "amax"
    )
    sigma = 0.4 * longest
    normals = torch.from_numpy(vertex_normals(vertices.detach().cpu(), faces.cpu())).to(vertices)
    scales = torch.stack([sigma, sigma, thickness * sigma], dim=-1)
    return SurfaceGaussians(vertices, quat_from_z(normals), scales, normals)


def render_demo(model: BodyModel, width: int = 384, height: int = 512, yaws=(0.0, 40.0)) -> Tensor:
    """The demo pose seen from each yaw, side by side: [height, width * len(yaws), 3] in [0, 1]."""
    params = model.params_from_pose(DEMO_POSE)
    with torch.no_grad():
        verts = model(params).vertices[0]
    keep = model.surface_vertex_mask
    # Faces whose three vertices are all kept, renumbered onto the kept vertices.
    index = torch.full((len(verts),), -1, dtype=torch.int64)
    index[keep] = torch.arange(int(keep.sum()))
    faces = index[model.faces]
    faces = faces[(faces >= 0).all(dim=-1)]
    g = surface_gaussians(verts[keep], faces)
    base = torch.tensor(PART_COLORS)[model.part_ids[keep]]
    light = torch.tensor([0.3, 0.5, 0.8])
    shade = 0.35 + 0.65 * (g.normals @ (light / light.norm())).clamp_min(0.0)
    colors = base * shade[:, None]
    opacities = torch.full((len(g.means),), 0.95)
    K = intrinsics(width, height, fov_y_deg=40.0)
    background = torch.ones(3)
    views = []
    for yaw in yaws:
        out = rasterize(
            g.means,
            g.quats,
            g.scales,
            opacities,
            colors,
            orbit_camera(yaw, 5.0, 2.7),
            K,
            width,
            height,
            background=background,
        )
        views.append(out.image.clamp(0, 1))
    return torch.cat(views, dim=1)


def signer_video(folder: Path, model: BodyModel, seed: int = 0) -> tuple[Path, Tensor]:
    """A video of the synthetic wild signer (256 px, 12 frames; MediaPipe finds body, face and
    hands) written to ``folder/signer.mp4``; returns it and its frames [N, H, W, 3] in [0, 1]."""
    from eva_engine.data import load_dataset, write_video
    from eva_engine.synth import generate

    ds = load_dataset(generate("wild", "small", seed, folder / "synthetic", model=model, overwrite=True))
    frames = ds.images(sorted(ds.splits["train"] + ds.splits["test_pose"]))
    video = write_video(folder / "signer.mp4", (frames.numpy() * 255 + 0.5).astype("uint8"), fps=ds.meta.fps)
    return video, frames
