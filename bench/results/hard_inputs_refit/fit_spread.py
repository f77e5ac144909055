"""Where a hard clip's fit is inconsistent: per body part, the image displacement of the fitted
mesh's vertices from the true mesh's (each projected by its own camera; the same vertex of one
topology), split into each vertex's mean over the clip (a bias the avatar can absorb: it is
trained in the fitted camera) and the frame-to-frame spread around it (what smears the avatar).
``python fit_spread.py <work folder of bench hard_inputs> <seed> <case>...``; prints Markdown."""

import sys

import numpy as np
import torch

from eva_engine.body import PART_NAMES, load_body_model
from eva_engine.data import load_dataset
from eva_engine.geometry import project_points, to_camera
from eva_engine.synth.hard import hard_scene

torch.set_num_threads(1)
work, seed, cases = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
model = load_body_model("anny")
print("| case | " + " | ".join(f"{p}: mean / spread (px)" for p in PART_NAMES) + " | fitted / true depth |")
print("|---|" + "---:|" * (len(PART_NAMES) + 1))
for case in cases:
    ds = load_dataset(f"{work}/{case}_cap10_s{seed}/dataset")
    h, w = ds.image_size
    scene = hard_scene(case, seed, frames=40, size=w, model=model)
    index = [int(np.abs(scene.times - float(t)).argmin()) for t in ds.timestamps]
    with torch.no_grad():
        fitted = to_camera(model(ds.params).vertices, ds.viewmat)
        true = to_camera(model(scene.sharp_params[torch.tensor(index)]).vertices, scene.viewmat[index])
    uv_fit = project_points(fitted, ds.K)
    uv_true = project_points(true, scene.K.expand(len(index), 3, 3))
    seen = (uv_true >= 0).all(-1) & (uv_true[..., 0] < w) & (uv_true[..., 1] < h)  # [F, V]
    shift = uv_fit - uv_true  # [F, V, 2]
    cells = []
    for p in range(len(PART_NAMES)):
        s, m = shift[:, model.part_ids == p], seen[:, model.part_ids == p]
        bias = (s * m[..., None]).sum(0) / m.sum(0).clamp_min(1)[:, None]  # [Vp, 2] over its seen frames
        cells.append(f"{s.norm(dim=-1)[m].mean():.1f} / {(s - bias).norm(dim=-1)[m].mean():.1f}")
    depth = float((fitted[..., 2].mean(1) / true[..., 2].mean(1)).mean())
    print(f"| {case} | " + " | ".join(cells) + f" | {depth:.2f} |")
