"""The synthetic benchmark: a textured Anny subject signing in front of a static camera, rendered
by a triangle-mesh rasterizer (``data.mesh_render``, not Gaussians), written in the dataset
layout with ground truth.

Presets (modelled on the paper's data):

- ``controlled`` (XHumans-like): full body, a slow whole-body turn; ground-truth parameters and
  keypoints are given to the pipeline.
- ``wild`` (UPB-like): a waist-up signer; the pipeline gets only images (it must detect and
  align); the ground truth is kept under ``ground_truth/`` for evaluation.

Sizes: ``tiny`` (96 px, 12 frames, for tests) and ``bench`` (512 px, 150 frames). Splits as in
the paper's appendix: every third frame of the sequence is a novel-pose test frame (interleaved,
as UPB), the rest train; ``test_view`` frames show training poses from a camera turned 35 deg
about the subject. Everything is deterministic given the seed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from eva_engine.body.model import PART_NAMES
from eva_engine.data.dataset import DatasetMeta, DatasetWriter, ParamNames
from eva_engine.data.look import Look, bake_texture, face_segments
from eva_engine.data.mesh_render import MeshRenderConfig, MeshRenderer, intrinsics, look_at
from eva_engine.data.motion import MotionConfig, sign_motion


@dataclasses.dataclass(frozen=True)
class Preset:
    """What the scene shows and what the pipeline is given."""

    name: str
    camera_target: tuple[float, float, float]
    """Point the camera looks at (world, metres)."""
    distance: float
    fov_y_deg: float
    body_turn: float
    """Amplitude (radians) of the slow whole-body turn."""
    give_ground_truth: bool
    """Write the ground-truth parameters and keypoints as pipeline inputs too."""
    view_angle_deg: float = 35.0
    """The held-out camera, turned about the vertical axis through the target."""


@dataclasses.dataclass(frozen=True)
class Size:
    """Resolution and length."""

    name: str
    image_size: int
    num_frames: int
    """Frames of the sequence (train + test_pose)."""
    num_view_frames: int
    supersample: int
    texture_size: int
    test_every: int = 3
    test_offset: int = 2


PRESETS: dict[str, Preset] = {
    "controlled": Preset("controlled", (0.0, 0.17, 0.0), 3.2, 40.0, body_turn=0.5, give_ground_truth=True),
    "wild": Preset("wild", (0.0, 0.42, 0.0), 2.45, 30.0, body_turn=0.15, give_ground_truth=False),
}
SIZES: dict[str, Size] = {
    "tiny": Size("tiny", 96, 12, 3, supersample=3, texture_size=512),
    # Large enough for a real detector (MediaPipe needs ~15 px palms), small enough for tests.
    "small": Size("small", 256, 12, 3, supersample=2, texture_size=1024),
    "bench": Size("bench", 512, 150, 30, supersample=2, texture_size=2048),
}
MOTION_SECONDS = 6.0
FACE_PART = {"hand.L": "hand", "hand.R": "hand", "body": "body", "foot.L": "body", "foot.R": "body"}


def project(
    vertices: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection. vertices: [B, V, 3] world; viewmat: [4, 4] or [B, 4, 4]; K: [3, 3] or
    [B, 3, 3]. Returns pixel coordinates [B, V, 2] (pixel (x, y) spans [x, x+1) x [y, y+1), so
    ``floor`` gives the pixel) and camera depth [B, V]."""
    view = viewmat.to(vertices.dtype)
    K_ = K.to(vertices.dtype)
    cam = vertices @ view[..., :3, :3].transpose(-1, -2) + view[..., None, :3, 3]
    z = cam[..., 2]
    safe = torch.where(z.abs() > 1e-9, z, torch.full_like(z, 1e-9))
    x, y = cam[..., 0] / safe, cam[..., 1] / safe
    u = K_[..., None, 0, 0] * x + K_[..., None, 0, 1] * y + K_[..., None, 0, 2]
    v = K_[..., None, 1, 1] * y + K_[..., None, 1, 2]
    return torch.stack([u, v], dim=-1), z


def splits(size: Size) -> tuple[dict[str, list[int]], list[int]]:
    """The split design for ``size`` and, per frame, the sequence frame whose pose it shows."""
    n = size.num_frames
    test = [i for i in range(n) if i % size.test_every == size.test_offset]
    train = [i for i in range(n) if i not in set(test)]
    picks = (
        np.linspace(0, len(train) - 1, size.num_view_frames).round().astype(int)
        if size.num_view_frames
        else []
    )
    view_src = [train[i] for i in picks]
    out = {"train": train, "test_pose": test, "test_view": list(range(n, n + len(view_src)))}
    return out, list(range(n)) + view_src


def cameras(preset: Preset, size: Size) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """K [3, 3], the training viewmat [4, 4] and the held-out viewmat [4, 4]."""
    target = np.asarray(preset.camera_target)
    a = math.radians(preset.view_angle_deg)
    main = look_at(target + (0.0, 0.0, preset.distance), target)
    side = look_at(target + preset.distance * np.array([math.sin(a), 0.0, math.cos(a)]), target)
    return intrinsics(size.image_size, size.image_size, preset.fov_y_deg), main, side


def random_shape(model, rng: np.random.Generator) -> torch.Tensor:
    """An adult Anny phenotype [1, S] (gender, age, muscle, weight, height, proportions)."""
    ranges = {"gender": (0.0, 1.0), "age": (0.45, 0.75), "muscle": (0.3, 0.7), "weight": (0.3, 0.7),
              "height": (0.3, 0.7), "proportions": (0.4, 0.6)}  # fmt: skip
    values = [rng.uniform(*ranges.get(name, (0.45, 0.55))) for name in model.shape_names]
    return torch.tensor([values], dtype=model.dtype)


def generate(
    preset: str,
    size: str,
    seed: int,
    out: str | Path,
    *,
    model=None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a synthetic dataset into ``out`` (the layout of ``docs/dataset-format.md``) and
    return its path. ``model``: an Anny body model (loaded if None); ``progress(done, total)``
    is called after every frame."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {list(PRESETS)}")
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r}; choose one of {list(SIZES)}")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if model is None:
        from eva_engine.body import load_body_model

        model = load_body_model("anny")
    if model.name != "anny":
        raise ValueError(f"the synthetic benchmark renders Anny, got body model {model.name!r}")
    p, s = PRESETS[preset], SIZES[size]
    split, pose_of_frame = splits(s)
    fps = s.num_frames / MOTION_SECONDS
    times = np.arange(s.num_frames) / fps
    rng = np.random.default_rng([seed, 1])
    shape = random_shape(model, rng)
    look = Look.random(rng)
    K, view_main, view_side = cameras(p, s)
    meta = DatasetMeta(
        source="synthetic",
        fps=fps,
        image_size=(s.image_size, s.image_size),
        name=f"{preset}-{size}-seed{seed}",
        body_model="anny",
        background=(1.0, 1.0, 1.0),
        camera_source="ground_truth",
    )
    motion_cfg = MotionConfig(duration=MOTION_SECONDS, body_turn=p.body_turn)
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        seq = sign_motion(model, shape, times, seed, motion_cfg)
        params = seq[pose_of_frame]
        with torch.no_grad():
            posed = model(params)
            keypoints3d = model.keypoints(posed)
        views = [view_main if i < s.num_frames else view_side for i in range(len(pose_of_frame))]
        viewmats = torch.stack(views)
        uv, depth = project(keypoints3d, viewmats, K)
        h = w = s.image_size
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h) & (depth > 0)
        keypoints = torch.cat([uv, inside[..., None].to(uv.dtype)], dim=-1).float()
        from eva_engine.body.anny_backend import SEGMENT_LABELS

        seg = face_segments(model)
        part = torch.tensor([PART_NAMES.index(FACE_PART.get(SEGMENT_LABELS[x], "face")) for x in seg])
        config = MeshRenderConfig(width=w, height=h, supersample=s.supersample, background=(1.0, 1.0, 1.0))
        with MeshRenderer(model.faces, config, num_vertices=model.num_vertices) as renderer:
            texture = bake_texture(
                model, params[0], look, renderer, s.texture_size, seed=seed, face_label=seg
            )
            renderer.set_surface(
                texture=texture,
                uv=model.anny.texture_coordinates.cpu().numpy(),
                face_uv=model.anny.face_texture_coordinate_indices.cpu().numpy(),
            )
            total = len(pose_of_frame)
            for i, src in enumerate(pose_of_frame):
                r = renderer.render(posed.vertices[i], views[i], K)
                writer.add_frame(
                    r.rgb.numpy(), r.alpha.numpy(), K=K, viewmat=views[i], time=float(times[src]),
                    hand_mask=r.label_coverage(part, PART_NAMES.index("hand")).numpy(),
                    face_mask=r.label_coverage(part, PART_NAMES.index("face")).numpy(),
                )  # fmt: skip
                if progress is not None:
                    progress(i + 1, total)
        give = p.give_ground_truth
        return writer.finish(
            split,
            params=params if give else None, params_names=ParamNames.of(model), params_source="ground_truth",
            keypoints=keypoints if give else None, keypoint_names=list(model.keypoint_names),
            keypoints_source="ground_truth", gt_params=params, gt_keypoints=keypoints,
            extra={
                "generator": "eva_engine.data.synthetic", "preset": preset, "size": size, "seed": seed,
                "pose_of_frame": pose_of_frame, "look": dataclasses.asdict(look),
                "view_angle_deg": p.view_angle_deg, "motion": dataclasses.asdict(motion_cfg),
                "renderer": "moderngl/llvmpipe textured mesh, Lambert", "supersample": s.supersample,
            },
        )  # fmt: skip
