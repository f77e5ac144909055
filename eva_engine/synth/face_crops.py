"""Face close-ups of a synthetic dataset, rendered: what ``eva preprocess`` cuts from a video
larger than its frames (``data.face_crops``), for a dataset that has no larger video.

The close-up's camera is the frame's restricted to the square around the face (the square the
product would cut: ``crop_boxes`` over the face-mesh landmarks), drawn by the mesh renderer at
``FaceCropConfig.size`` px with the dataset's subject, texture and light. Trained with
``face_view.weight > 0`` on such a dataset, an avatar sees what it sees on a 1080p talking-head
clip, and the synthetic novel-view splits can score what the close-ups do to views of the head
that training never showed (``bench novel_pose --face-crops``).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from eva_engine.data.dataset import load_dataset
from eva_engine.data.face_crops import (
    FaceCropConfig,
    FaceCrops,
    crop_boxes,
    crop_intrinsics,
    store_face_crops,
)
from eva_engine.progress import Progress, ProgressEvent
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer
from eva_engine.synth.benchmark import GENERATOR, PRESETS, SIZES
from eva_engine.synth.texture import Look, apply_look


def render_face_crops(
    dataset_root: str | Path,
    face_mesh: Tensor,
    *,
    model=None,
    config: FaceCropConfig = FaceCropConfig(),
    progress: Progress | None = None,
) -> FaceCrops | None:
    """Render and store the close-ups of the synthetic dataset at ``dataset_root`` (replacing any
    it had); None when its faces are too small for them (``config.min_side``) or a close-up of
    ``config.size`` px would hold under ``config.min_gain`` times a frame's pixels. Frames whose
    face is not wholly inside the frame get none.

    face_mesh: [N, 478, >=3] the true face's MediaPipe landmarks in each frame's pixels (x, y, and
    0 where a landmark has no point), e.g. ``eval.expression_fidelity.fitted_landmarks`` of the
    ground truth. model: the Anny body model (loaded if None). ``progress`` hears stage
    "face crops" after every close-up."""
    ds = load_dataset(dataset_root)
    extra = ds.meta.extra
    if extra.get("generator") != GENERATOR or ds.gt_params is None:
        raise ValueError(f"{ds.root} is not a synthetic benchmark dataset with its ground truth")
    if face_mesh.shape[0] != ds.meta.num_frames:
        raise ValueError(f"face_mesh has {face_mesh.shape[0]} frames, the dataset {ds.meta.num_frames}")
    if model is None:
        from eva_engine.body import load_body_model

        model = load_body_model("anny")
    preset, size = PRESETS[extra["preset"]], SIZES[extra["size"]]
    h, w = ds.meta.image_size
    boxes = crop_boxes(face_mesh, (h, w), config)
    # A face the frame cuts (a tall subject's head above a fixed camera's view) is one the
    # detector would not find in a video: no close-up of what the frame does not show.
    xy, found = face_mesh[..., :2], face_mesh[..., 2] > 0
    inside = (xy[..., 0] >= 0) & (xy[..., 0] < w) & (xy[..., 1] >= 0) & (xy[..., 1] < h)
    boxes[~(inside | ~found).all(dim=1)] = 0.0
    wanted = [int(i) for i in torch.nonzero(boxes[:, 2] > 0).flatten()]
    side = config.size
    if not wanted or side / float(boxes[wanted, 2].median()) < config.min_gain:
        return store_face_crops(ds.root, boxes, side, [None], config)
    render_config = MeshRenderConfig(
        width=side,
        height=side,
        supersample=size.supersample,
        background=tuple(ds.meta.background or (1.0, 1.0, 1.0)),
        light=preset.light,
        light_frame="world",
    )

    def rendered(renderer: MeshRenderer) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        for done, i in enumerate(wanted, 1):
            with torch.no_grad():
                vertices = model(ds.gt_params[i]).vertices[0]
            out = renderer.render(vertices, ds.viewmat[i], crop_intrinsics(ds.K[i], boxes[i], side))
            yield i, _to_uint8(out.rgb), _to_uint8(out.alpha)
            if progress is not None:
                progress(ProgressEvent("face crops", done, len(wanted), f"close-up {done}/{len(wanted)}"))

    look = Look(**{k: tuple(v) for k, v in extra["look"].items()})
    with MeshRenderer(model.faces, render_config, num_vertices=model.num_vertices) as renderer:
        apply_look(renderer, model, ds.gt_params[0], look, size.texture_size, seed=int(extra["seed"]))
        return store_face_crops(ds.root, boxes, side, rendered(renderer), config)


def _to_uint8(a: Tensor) -> np.ndarray:
    return (a.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
