"""Synthetic ``wild``'s 150 frames fitted from MediaPipe's detections with a given calibration (the
fit of ``../variants.py``, ``hand_depth_scale`` 1):
``python wild_fit.py <calibration.json | shipped | none>``, one thread. The detections are
cached in ``$TMPDIR/wild_detections.pkl`` (MediaPipe Holistic, as the product detects)."""

import os
import pickle
import sys
import tempfile
import time

import numpy as np
import torch

import eva_engine.align.face_calibration as fc
import eva_engine.align.objective as objective
from eva_engine.align.clip import fit_clip
from eva_engine.align.evaluate import expression_error, expression_error_by_group
from eva_engine.align.stages import FitConfig
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.paths import data_dir

torch.set_num_threads(1)
which = sys.argv[1]
model = load_body_model("anny")
ds = load_dataset(data_dir() / "synthetic" / "wild-bench-seed0")
order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:150]
K, view = ds.K[order], ds.viewmat[order]
truth = ds.gt_params.map(lambda t: t[order])
cache = os.path.join(tempfile.gettempdir(), "wild_detections.pkl")
if os.path.exists(cache):
    with open(cache, "rb") as f:
        detections = pickle.load(f)
else:
    from eva_engine.align import detect_frames

    images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    detections = detect_frames(iter(images)).targets(K, view)
    with open(cache, "wb") as f:
        pickle.dump(detections, f)
if which not in ("none", "shipped"):
    with open(which) as f:
        calibration = fc.DetectorCalibration.from_json(__import__("json").load(f))
    objective.load_calibration = lambda *a, **k: calibration
t0 = time.time()
fit = fit_clip(
    model,
    detections,
    ds.timestamps[order],
    FitConfig(hand_depth_scale=1.0, detector_calibration=which != "none"),
)
groups = expression_error_by_group(model, fit.params, truth)
print(
    f"{which}: expression {expression_error(model, fit.params, truth):.3f} mm,",
    {k: round(v, 2) for k, v in groups.items()},
    f"{time.time() - t0:.0f} s",
)
