"""The expression fit's floor: wild's clip fitted to exact targets *including* an exact face mesh
(the correspondence points of the true face, projected), with the face stage at N iterations."""

import dataclasses
import os
import sys
import time

import torch

from eva_engine.align.clip import fit_clip
from eva_engine.align.evaluate import expression_error, expression_error_by_group, targets_from_params
from eva_engine.align.face_mesh import load_correspondence
from eva_engine.align.stages import FitConfig
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.eval.expression_fidelity import fitted_landmarks
from eva_engine.paths import data_dir

torch.set_num_threads(1)
face_iters = int(sys.argv[1])
calib = sys.argv[2] == "1"
model = load_body_model("anny")
ds = load_dataset(data_dir() / "synthetic" / "wild-bench-seed0")
order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:150]
K, view = ds.K[order], ds.viewmat[order]
truth = ds.gt_params.map(lambda t: t[order])
exact = targets_from_params(model, truth, K, view, ds.image_size)
reg, ids = load_correspondence(model).regressor(model)
f = truth.batch_size
fm = fitted_landmarks(model, truth, reg, ids, K.expand(f, 3, 3), view.expand(f, 4, 4)).float()
mode = sys.argv[3] if len(sys.argv) > 3 else "exact"
if mode == "exact":
    exact = dataclasses.replace(exact, face_mesh=fm, face_depth=None)
else:
    import numpy as np

    from eva_engine.align import detect_frames

    images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    det = detect_frames(iter(images)).targets(K, view)
    if mode == "det":  # what the product fits: every detection
        exact = det
    else:  # "detface": exact body, detected face
        exact = dataclasses.replace(exact, face_mesh=det.face_mesh, face_depth=det.face_depth)
cfg = FitConfig(hand_depth_scale=1.0, detector_calibration=calib)

over = {}
if "W_OPEN" in os.environ:
    over["w_openings"] = float(os.environ["W_OPEN"])
if "EXPR_REG" in os.environ:
    over["expression_reg"] = float(os.environ["EXPR_REG"])
if "W_MESH" in os.environ:
    over["w_face_mesh"] = float(os.environ["W_MESH"])
stages = tuple(
    dataclasses.replace(s, **(over if s.name in ("face", "refine", "outline") else {})) for s in cfg.stages
)
stages = tuple(dataclasses.replace(s, iterations=face_iters) if s.name == "face" else s for s in stages)
print("overrides", over)
cfg = dataclasses.replace(cfg, stages=stages)
if len(sys.argv) > 4 and sys.argv[4] == "nolids":
    from mediapipe.python.solutions import face_mesh_connections as fmc

    import eva_engine.align.objective as obj

    eyes = {i for c in (fmc.FACEMESH_LEFT_EYE | fmc.FACEMESH_RIGHT_EYE) for i in c}
    orig = obj.load_calibration

    def patched(model):
        c = orig(model)
        keep = torch.tensor([int(k) not in eyes for k in c.landmarks], dtype=torch.float32)
        return dataclasses.replace(c, bias=c.bias * keep[:, None], gain=c.gain * keep[None, :, None])

    obj.load_calibration = patched
    print("eye landmarks uncalibrated:", len(eyes))
t0 = time.time()
fit = fit_clip(model, exact, ds.timestamps[order], cfg)
print(
    f"{mode} face iters {face_iters} calib {calib}:",
    f"expression {expression_error(model, fit.params, truth):.2f} mm,",
    {k: round(v, 2) for k, v in expression_error_by_group(model, fit.params, truth).items()},
    f"{time.time() - t0:.0f} s",
)
