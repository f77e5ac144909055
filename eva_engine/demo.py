"""The demo: the main job end to end on the embedded default, and a quick body-only scene.

``run_pipeline_demo`` (``eva demo``): a synthetic signer (the Anny body, rendered as a mesh) is
written as a video, then the product's pipeline runs on it -- ``preprocess_video`` (MediaPipe
detection + body-model alignment), ``train_avatar``, ``save_avatar`` -- and the avatar is
rendered in the input pose and in a new pose (a wave, curled fingers, a smile) from the input
camera and from 35 degrees to the side.

``render_demo`` (``eva demo --body-only``): the posed body model as surface Gaussians rendered
by ``eva_engine.render`` -- the body model and rasterizer alone, in a second.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from eva_engine.body import BodyModel
from eva_engine.data.mesh_render import vertex_normals
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


def quat_from_z(directions: Tensor) -> Tensor:
    """[N, 3] unit vectors -> [N, 4] (w, x, y, z) shortest rotations taking +z onto them."""
    z = torch.zeros_like(directions)
    z[:, 2] = 1.0
    w = 1.0 + directions[:, 2:3]
    q = torch.cat([w, torch.linalg.cross(z, directions)], dim=-1)
    # Opposite to +z: any half turn about an axis orthogonal to z.
    flip = w[:, 0] < 1e-6
    q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype)
    return q / q.norm(dim=-1, keepdim=True)


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
            g.means, g.quats, g.scales, opacities, colors, orbit_camera(yaw, 5.0, 2.7), K, width, height,
            background=background,
        )  # fmt: skip
        views.append(out.image.clamp(0, 1))
    return torch.cat(views, dim=1)


@dataclass
class PipelineDemo:
    """Where ``run_pipeline_demo`` wrote things, and what it measured."""

    image: Path
    video: Path
    dataset: Path
    avatar: Path
    seconds: dict[str, float]
    num_gaussians: int
    psnr_input_pose: float


def run_pipeline_demo(
    workdir: Path,
    out_png: Path,
    preset_name: str = "fast",
    iterations: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> PipelineDemo:
    """Video -> dataset -> avatar -> renders (see the module docstring). Everything it writes
    goes under ``workdir`` (replaced on every run) except the PNG."""
    import shutil

    import numpy as np
    from PIL import Image

    from eva_engine.align import PreprocessConfig, preprocess_video
    from eva_engine.avatar import save_avatar
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset, write_video
    from eva_engine.data.synthetic import generate
    from eva_engine.metrics import psnr
    from eva_engine.render import Camera
    from eva_engine.train import preset, train_avatar

    def say(msg: str) -> None:
        if progress is not None:
            progress(msg)

    seconds: dict[str, float] = {}
    workdir = Path(workdir)
    shutil.rmtree(workdir, ignore_errors=True)
    workdir.mkdir(parents=True)
    model = load_body_model("anny")

    t0 = time.perf_counter()
    say("rendering a synthetic signer video (Anny, mesh renderer)")
    synth = load_dataset(generate("wild", "small", 0, workdir / "synthetic", model=model))
    order = sorted(synth.splits["train"] + synth.splits["test_pose"])
    frames = (synth.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    video = write_video(workdir / "signer.mp4", frames, fps=synth.meta.fps)
    seconds["video"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    say("preprocessing: MediaPipe detection and body-model alignment")
    preprocess_video(video, workdir / "dataset", PreprocessConfig(test_every=4), model=model)
    dataset = load_dataset(workdir / "dataset")
    seconds["preprocess"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    overrides = {} if iterations is None else {"iterations": iterations}
    config = preset(preset_name, **overrides)
    say(f"training the avatar ({preset_name} preset, {config.iterations} iterations)")
    result = train_avatar(dataset, config, body=model)
    avatar = result.avatar
    save_avatar(avatar, workdir / "avatar", {"train_seconds": result.train_seconds, "demo": True})
    seconds["train"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    say("rendering the avatar")
    h, w = dataset.image_size
    i = dataset.splits["test_pose"][0]  # a frame the avatar was not trained on
    K, view = dataset.K[i], dataset.viewmat[i]
    observed = dataset.params.map(lambda t: t[i : i + 1].clone())
    novel = observed.map(lambda t: t.clone())
    wave = model.params_from_pose(DEMO_POSE)
    novel.joints, novel.expression = wave.joints.clone(), wave.expression.clone()
    with torch.no_grad():
        centre = model(observed).joints[0].mean(0)
        side = view @ _turn_about(centre, math.radians(35.0))
        white = torch.ones(3)
        panels = [
            dataset.image(i),
            avatar.render(observed, Camera(K, view, w, h), white),
            avatar.render(novel, Camera(K, view, w, h), white),
            avatar.render(novel, Camera(K, side, w, h), white),
        ]
    target = dataset.image(i) * dataset.mask(i)[..., None] + (1 - dataset.mask(i)[..., None])
    quality = float(psnr(panels[1].clamp(0, 1).permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]))
    strip = torch.cat([p.clamp(0, 1) for p in panels], dim=1).numpy()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((strip * 255 + 0.5).astype(np.uint8)).save(out_png)
    seconds["render"] = time.perf_counter() - t0
    return PipelineDemo(
        out_png, video, workdir / "dataset", workdir / "avatar", seconds, len(avatar.gaussians), quality
    )


def _turn_about(centre: Tensor, angle: float) -> Tensor:
    """[4, 4] world transform turning points by ``angle`` about the vertical axis through ``centre``."""
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    m = torch.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = centre - rot @ centre
    return m
