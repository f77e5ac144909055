import cv2
import numpy as np
import torch

from eva_engine.avatar.io import load_avatar
from eva_engine.data import load_dataset
from eva_engine.render import Camera

ds = load_dataset("data/synthetic/controlled-bench-seed0")
AVATARS = "<avatars>"  # the folder the eva train commands of the README wrote
avatars = {w: load_avatar(f"{AVATARS}/w{w}") for w in (128, 64)}
rows = []
for i in ds.splits["test_view"][::10][:3]:
    f = ds[i]
    cam = Camera(f.K, f.viewmat, f.image.shape[1], f.image.shape[0])
    row = [f.image.numpy()]
    for av in avatars.values():
        with torch.no_grad():
            row.append(av.render(ds.params[i : i + 1], cam).numpy())
    rows.append(np.concatenate(row, 1))
img = (np.concatenate(rows, 0) * 255).clip(0, 255).astype(np.uint8)
cv2.imwrite("test_view_sheet.png", cv2.resize(img, None, fx=0.5, fy=0.5)[..., ::-1])
print("ok", img.shape)
