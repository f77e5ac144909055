"""The training camera's face in the 512 px frame, enlarged (nearest) to 240 px: truth | the default |
the face close-ups (classic rasterizer), for the novel-pose sheet's frames of seed 0.

The two avatars are trained outside the benchmark (it keeps none), as its rows train them:

    eva train data/synthetic/novel-bench-seed0 --out <tmp>/base-s0 --preset fast --threads 1 --seed 0 \
        --no-quality
    eva train data/synthetic/novel-bench-seed0 --out <tmp>/fc-s0 --preset fast --threads 1 --seed 0 \\
        --set face_view.weight=1 --no-quality
    python bench/results/novel_pose_closeups/frame_faces.py <tmp>
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image

from bench.novel_pose import dataset_for, sheet_frames
from eva_engine.avatar import Camera, load_saved_avatar
from eva_engine.data import load_dataset
from eva_engine.train.losses import composite_target


def main(avatars: Path) -> None:
    ds = load_dataset(dataset_for("bench", 0, face_crops=True))
    models = [load_saved_avatar(avatars / name).avatar.eval() for name in ("base-s0", "fc-s0")]
    white, rows = torch.ones(3), []
    for i in sheet_frames(ds)[:3]:  # near, far and view at 35 deg: the training camera's side
        frame = ds[i]
        x0, y0, side = (int(v) for v in ds.face_crops.boxes[i].tolist())
        cam = Camera(frame.K.float(), frame.viewmat.float(), *frame.image.shape[1::-1])
        images = [composite_target(frame.image, frame.mask, white)]
        with torch.no_grad():
            images += [m(ds.gt_params[i], cam, white).image.clamp(0, 1) for m in models]
        tiles = [(t.numpy()[y0 : y0 + side, x0 : x0 + side] * 255 + 0.5).astype(np.uint8) for t in images]
        big = [cv2.resize(t, (240, 240), interpolation=cv2.INTER_NEAREST) for t in tiles]
        rows.append(np.concatenate(big, axis=1))
    out = Path(__file__).with_name("frame_faces_seed0.jpg")
    Image.fromarray(np.concatenate(rows, axis=0)).save(out, quality=90, optimize=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
