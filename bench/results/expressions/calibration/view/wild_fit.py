"""``variants.py 200 1 det`` (synthetic ``wild``, MediaPipe's detections, the face stage at 200)
with the calibration regressed from saved renders (``renders.py``) instead of the product's:

    CAL_DATA=renders.npz CAL_VIEW=none|v3 CAL_USE_VIEW=0|1 python wild_fit.py

``none``: the actions alone; ``v3``: the actions and the view's cubic terms, the view's gains
used by the fit (``CAL_USE_VIEW=1``, needs ``view_calibration.patch``) or dropped. Eye outlines
uncalibrated, as the product's. Run from the repository root."""

import os
import runpy
import sys

import numpy as np
import torch

import eva_engine.align.objective as obj
from eva_engine.align import face_calibration as fc

data = np.load(os.environ["CAL_DATA"])
kind = os.environ.get("CAL_VIEW", "v3")
use_view = os.environ.get("CAL_USE_VIEW", "1") == "1"
lms, x, r = data["lms"], data["X"], data["R"]
frontal = np.array([0.0, 0.5535])
cols = [np.ones((len(x), 1)), x]
if kind == "v3":
    u, v = data["D"][:, 0] - frontal[0], data["D"][:, 1] - frontal[1]
    cols.append(np.stack([u, v, u * u, v * v, u * v, u**3, v**3, u * u * v, u * v * v], 1))
a = np.concatenate(cols, 1)
w = np.linalg.solve(a.T @ a + fc.RIDGE * np.eye(a.shape[1]), a.T @ r.reshape(len(r), -1))
w = torch.from_numpy(w).float().reshape(a.shape[1], len(lms), 2)
w = w * torch.tensor([int(k) not in fc.EYE_CONTOURS for k in lms], dtype=torch.float32)[None, :, None]
e = x.shape[1]
view = (w[1 + e :], torch.tensor(frontal, dtype=torch.float32)) if kind == "v3" and use_view else ()
calibration = fc.DetectorCalibration(torch.from_numpy(lms), w[0], w[1 : 1 + e], *view)
obj.load_calibration = lambda *args, **kwargs: calibration
print("calibration", os.environ["CAL_DATA"], kind, "view used", bool(view))
sys.argv = ["variants.py", "200", "1", "det"]
runpy.run_path("bench/results/expressions/calibration/variants.py", run_name="__main__")
