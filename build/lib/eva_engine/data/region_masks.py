"""Per-frame region masks (the subject's left hand, right hand and face) from a posed body model.

The body model's part segmentation (``BodyModel.sided_part_ids``) is rendered with the frame's
camera by the triangle-mesh renderer (``render.mesh``), so a region's mask holds its
*visible* pixels after occlusion. With a person mask (a real video), each region is also
intersected with it: the fitted body tells which person pixels belong to a hand or the face, the
segmentation tells which pixels are the person. A region the caller marks as absent in a frame
(a hand neither detected nor fitted) gets an all-zero mask, which region metrics skip.

    masks = region_masks(model, params, K, viewmat, (h, w), person_masks=..., present=...)
    masks[i]["hand_left"]  # [H, W] float32 coverage in [0, 1]

With ``arms=True`` the masks also hold each arm (``ARM_REGIONS``: the body-part vertices that an
arm bone, shoulder to forearm, moves most), which the novel-pose benchmark scores.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from eva_engine.body.model import SIDED_PART_NAMES, BodyModel
from eva_engine.body.params import BodyParams
from eva_engine.data.dataset import REGION_MASKS
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer, MeshRenderOutput

ARM_REGIONS = ("arm_left", "arm_right")
ARM_JOINTS = {
    "arm_left": (
        "shoulder01.L",
        "upperarm01.L",
        "upperarm02.L",
        "lowerarm01.L",
        "lowerarm02.L",
        "left_elbow",
    ),
    "arm_right": (
        "shoulder01.R",
        "upperarm01.R",
        "upperarm02.R",
        "lowerarm01.R",
        "lowerarm02.R",
        "right_elbow",
    ),
}
"""Per arm, the joints (Anny's, and SMPL-X's elbow) whose vertices make it up."""


def _majority(vertex_labels: np.ndarray, faces: np.ndarray, count: int) -> np.ndarray:
    """[F] the label most of each triangle's corners carry (a seam triangle goes with two of
    its three corners)."""
    parts = vertex_labels[faces]  # [F, 3]
    counts = np.stack([(parts == p).sum(axis=1) for p in range(count)], axis=1)
    return counts.argmax(axis=1)


def arm_regions(model: BodyModel) -> np.ndarray:
    """[F] per triangle: 0, or 1 + the index into ``ARM_REGIONS`` of the arm it belongs to (its
    vertices are body-part vertices whose largest skinning weight is an arm joint)."""
    dominant = model.skinning_weights.argmax(dim=1).cpu().numpy()
    body = (model.part_ids == 0).cpu().numpy()
    labels = np.zeros(model.num_vertices, np.int64)
    for k, region in enumerate(ARM_REGIONS):
        ids = [model.joint_names.index(j) for j in ARM_JOINTS[region] if j in model.joint_names]
        labels[np.isin(dominant, ids) & body] = k + 1
    return _majority(labels, model.faces.cpu().numpy(), len(ARM_REGIONS) + 1)


def face_regions(model: BodyModel) -> np.ndarray:
    """[F] index into ``SIDED_PART_NAMES`` per triangle: the part most of its vertices belong to
    (a triangle on a seam goes with two of its three corners)."""
    return _majority(model.sided_part_ids.cpu().numpy(), model.faces.cpu().numpy(), len(SIDED_PART_NAMES))


def coverage_by_region(render: MeshRenderOutput, labels: np.ndarray) -> dict[str, np.ndarray]:
    """{region: [H, W] coverage} of the ``REGION_MASKS`` regions in a mesh render, given the
    per-triangle ``labels`` [F] of :func:`face_regions`."""
    lab = torch.from_numpy(labels)
    return {r: render.label_coverage(lab, SIDED_PART_NAMES.index(r)).numpy() for r in REGION_MASKS}


class RegionMaskRenderer:
    """Renders the region masks of one body model at one image size, frame after frame (one GL
    context for all of them); with ``arms``, each arm's too. Use as a context manager, or call
    :meth:`close`."""

    def __init__(
        self, model: BodyModel, image_size: tuple[int, int], supersample: int = 2, arms: bool = False
    ) -> None:
        h, w = image_size
        self.image_size = (h, w)
        self.labels = face_regions(model)
        self.arm_labels = arm_regions(model) if arms else None
        config = MeshRenderConfig(width=w, height=h, supersample=supersample)
        self.renderer = MeshRenderer(model.faces, config, num_vertices=model.num_vertices)

    def __enter__(self) -> RegionMaskRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.renderer.close()

    def __call__(
        self,
        vertices: torch.Tensor,
        viewmat: torch.Tensor,
        K: torch.Tensor,
        person_mask: np.ndarray | None = None,
        present: Sequence[bool] | None = None,
    ) -> dict[str, np.ndarray]:
        """{region: [H, W] float32} for posed ``vertices [V, 3]`` seen by ``viewmat [4, 4]``,
        ``K [3, 3]``; intersected with ``person_mask [H, W]`` if given; all-zero for the regions
        ``present`` (one bool per ``REGION_MASKS`` name) marks absent."""
        render = self.renderer.render(vertices, viewmat, K)
        cov = coverage_by_region(render, self.labels)
        if self.arm_labels is not None:
            lab = torch.from_numpy(self.arm_labels)
            cov |= {r: render.label_coverage(lab, k + 1).numpy() for k, r in enumerate(ARM_REGIONS)}
        if person_mask is not None:
            person = np.asarray(person_mask, np.float32)
            cov = {r: np.minimum(m, person) for r, m in cov.items()}
        for r, keep in zip(REGION_MASKS, present if present is not None else [True] * 3, strict=True):
            if not keep:
                cov[r] = np.zeros(self.image_size, np.float32)
        return cov


def region_masks(
    model: BodyModel,
    params: BodyParams,
    K: torch.Tensor,
    viewmat: torch.Tensor,
    image_size: tuple[int, int],
    person_masks: Sequence[np.ndarray] | None = None,
    present: np.ndarray | None = None,
    supersample: int = 2,
    batch: int = 32,
    arms: bool = False,
) -> list[dict[str, np.ndarray]]:
    """Region masks of N frames.

    params: ``BodyParams`` with N rows; K: [3, 3] or [N, 3, 3]; viewmat: [4, 4] or [N, 4, 4];
    image_size: (H, W); person_masks: N masks [H, W] in [0, 1] to intersect with (None: the
    render's own coverage); present: [N, len(REGION_MASKS)] bool, False where a region is not to
    be scored in that frame (None: all present); arms: add the ``ARM_REGIONS`` masks. Returns N
    dicts {region: [H, W] float32}.
    """
    n = params.batch_size
    K = K.expand(n, 3, 3) if K.ndim == 2 else K
    viewmat = viewmat.expand(n, 4, 4) if viewmat.ndim == 2 else viewmat
    if K.shape[0] != n or viewmat.shape[0] != n:
        raise ValueError(f"cameras for {K.shape[0]} / {viewmat.shape[0]} frames, params for {n}")
    if person_masks is not None and len(person_masks) != n:
        raise ValueError(f"{len(person_masks)} person masks for {n} frames")
    present = np.ones((n, len(REGION_MASKS)), bool) if present is None else np.asarray(present, bool)
    if present.shape != (n, len(REGION_MASKS)):
        raise ValueError(f"present must be [{n}, {len(REGION_MASKS)}], got {present.shape}")
    out: list[dict[str, np.ndarray]] = []
    with RegionMaskRenderer(model, image_size, supersample, arms=arms) as render:
        for start in range(0, n, batch):
            rows = list(range(start, min(start + batch, n)))
            with torch.no_grad():
                vertices = model(params[rows]).vertices
            for j, i in enumerate(rows):
                person = person_masks[i] if person_masks is not None else None
                out.append(render(vertices[j], viewmat[i], K[i], person, present[i]))
    return out
