"""A contact sheet of a dataset: per chosen frame, the full image and close-ups of the face and
both hands (boxes from the ground-truth keypoints), so a reader can see the detail that matters."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from eva_engine.body.keypoints import KEYPOINT_GROUPS


def _crop_box(points: torch.Tensor, h: int, w: int, pad: float, min_size: int) -> tuple[int, int, int, int]:
    """Square box (x0, y0, x1, y1) around visible points [K, 3], grown by ``pad`` of its size."""
    vis = points[points[:, 2] > 0, :2]
    if len(vis) == 0:
        return 0, 0, w, h
    lo, hi = vis.min(0).values, vis.max(0).values
    centre = (lo + hi) / 2
    side = max(float((hi - lo).max()) * (1 + 2 * pad), float(min_size))
    side = min(side, float(min(h, w)))
    x0 = int(round(min(max(float(centre[0]) - side / 2, 0.0), w - side)))
    y0 = int(round(min(max(float(centre[1]) - side / 2, 0.0), h - side)))
    return x0, y0, x0 + int(side), y0 + int(side)


def contact_sheet(dataset, indices: Sequence[int], tile: int = 256, pad: float = 0.35) -> np.ndarray:
    """Rows of [full frame, face, left hand, right hand] tiles for ``indices`` of a dataset with
    keypoints (ground truth preferred). Returns uint8 [len(indices) * tile, 4 * tile, 3]."""
    import cv2

    kp_all = dataset.gt_keypoints if dataset.gt_keypoints is not None else dataset.keypoints
    if kp_all is None:
        raise ValueError("the dataset has no keypoints to place the close-ups")
    h, w = dataset.image_size
    rows = []
    for i in indices:
        img = (dataset.image(i).numpy() * 255).round().astype(np.uint8)
        tiles = [cv2.resize(img, (tile, tile), interpolation=cv2.INTER_AREA)]
        for group in ("face", "left_hand", "right_hand"):
            pts = kp_all[i, KEYPOINT_GROUPS[group]]
            if group == "face":  # the face points are inner features: widen to the whole head
                pad_g, min_size = pad + 0.45, max(8, h // 12)
            else:
                pad_g, min_size = pad, max(8, h // 10)
            x0, y0, x1, y1 = _crop_box(pts, h, w, pad_g, min_size)
            crop = img[y0:y1, x0:x1]
            interp = cv2.INTER_AREA if crop.shape[0] > tile else cv2.INTER_CUBIC
            tiles.append(cv2.resize(crop, (tile, tile), interpolation=interp))
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)
