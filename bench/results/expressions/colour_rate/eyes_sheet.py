"""The eyes on a clip's three most closed test frames, at four times the frame's pixels: target |
each avatar given. From the repository:

    PYTHONPATH=. python bench/results/expressions/colour_rate/eyes_sheet.py <dataset> <out.jpg> <avatar>...

(the target upsampled bicubically; MediaPipe's lid gap picks the frames)."""

import sys

import numpy as np
import torch
from PIL import Image

from bench.blink_sweep import signed_lid_gap
from eva_engine.avatar import Camera, load_saved_avatar
from eva_engine.data import load_dataset

SCALE = 4


def main(dataset: str, out: str, avatars: list[str]) -> None:
    torch.set_num_threads(1)
    ds = load_dataset(dataset)
    stored = ds.keypoint_extras["face_mesh"]
    test = ds.splits["test_pose"]
    gaps = [signed_lid_gap(stored[i]) if stored[i, :468, 2].amax() > 0 else np.inf for i in test]
    frames = [test[j] for j in np.argsort(gaps)[:3]]
    models = [load_saved_avatar(a).avatar.eval() for a in avatars]
    rows = []
    for i in frames:
        f = ds[i]
        h, w = f.image.shape[:2]
        cam = Camera(f.K.float(), f.viewmat.float(), w, h).scaled(SCALE)
        xy = stored[i, :468, :2] * SCALE
        (x0, y0), (x1, y1) = xy.min(0).values.int().tolist(), xy.max(0).values.int().tolist()
        y1 = y0 + (y1 - y0) * 3 // 5  # brows to nose
        target = Image.fromarray((f.image.clamp(0, 1).numpy() * 255).astype(np.uint8))
        tiles = [np.array(target.resize((w * SCALE, h * SCALE), Image.BICUBIC))[y0:y1, x0:x1]]
        for av in models:
            with torch.no_grad():
                img = av(ds.params[[i]][0], cam, torch.ones(3)).image
            tiles.append((img.clamp(0, 1).numpy() * 255).astype(np.uint8)[y0:y1, x0:x1])
        rows.append(np.concatenate(tiles, axis=1))
    width = min(r.shape[1] for r in rows)
    Image.fromarray(np.concatenate([r[:, :width] for r in rows], axis=0)).save(out, quality=90)
    print(out, "frames", frames)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
