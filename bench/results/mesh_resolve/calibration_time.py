"""The face mesh's calibration built once (the Anny cache and the correspondence present): its
wall time, and two numbers that identify the result."""

import time

from eva_engine.align.face_calibration import build_calibration
from eva_engine.align.face_mesh import load_correspondence
from eva_engine.body import load_body_model

model = load_body_model("anny")
correspondence = load_correspondence(model)
start = time.perf_counter()
calibration = build_calibration(model, correspondence)
seconds = time.perf_counter() - start
print(
    f"build_calibration {seconds:.1f} s",
    float(calibration.gain.abs().max()),
    float(calibration.bias.abs().sum()),
)
