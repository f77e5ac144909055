"""The detector's calibration built from another random draw of expressions (``SEED``), or from
renders shrunk to a smaller face: ``python build.py <eye-corner px> <out.json> [samples]``.

The 512 px close-up (eye corners 137 px apart) is shrunk by area to the given eye-corner distance
and pasted centred on a 512 px canvas of its background before MediaPipe reads it; its landmarks
are scaled back. 137 or more: the product's renders, unchanged."""

import json
import os
import sys

import cv2
import numpy as np

import eva_engine.align.face_calibration as fc
from eva_engine.align.face_mesh import load_correspondence
from eva_engine.body import load_body_model

CLOSE_UP_EYE_PX = 137.36  # the 512 px close-up's eye-corner distance (neutral face, head-on)
eye_px, out = float(sys.argv[1]), sys.argv[2]
samples = int(sys.argv[3]) if len(sys.argv) > 3 else fc.SAMPLES
read = fc.face_mesh_pixels


def shrunk(detector, rgb):
    s = eye_px / CLOSE_UP_EYE_PX
    if s >= 0.99:  # 137 px: the product's renders, unchanged
        return read(detector, rgb)
    n = max(8, round(512 * s))
    canvas = np.empty_like(rgb)
    canvas[:] = rgb[0, 0]
    o = (512 - n) // 2
    canvas[o : o + n, o : o + n] = cv2.resize(rgb, (n, n), interpolation=cv2.INTER_AREA)
    marks = read(detector, canvas)
    return None if marks is None else (marks - o) * (512 / n)


fc.face_mesh_pixels = shrunk
model = load_body_model("anny")
calibration = fc.build_calibration(
    model, load_correspondence(model), samples=samples, seed=int(os.environ.get("SEED", 0))
)
with open(out, "w") as f:
    json.dump(calibration.to_json(), f)
print("saved", out)
