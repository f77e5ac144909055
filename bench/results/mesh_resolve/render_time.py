"""One 512² render of the calibration's painted face (supersample 2) and MediaPipe on it: the mean
over 10 expressions x 3 views. ``python render_time.py <torch threads>``."""

import sys
import time

import numpy as np
import torch
from mediapipe.python.solutions import face_mesh as mp_face_mesh

from eva_engine.align.face_mesh import face_mesh_pixels, head_camera, painted_face_renderer
from eva_engine.body import load_body_model

torch.set_num_threads(int(sys.argv[1]))
model = load_body_model("anny")
cameras = [head_camera(model, yaw, pitch, 512) for yaw, pitch in ((0.0, 0.0), (-15.0, 5.0), (15.0, -5.0))]
posing = rendering = detecting = 0.0
detector = mp_face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True)
with painted_face_renderer(model, 512) as renderer, detector:
    for i in range(10):
        params = model.default_params(1)
        params.expression[0, i] = 0.7
        t = time.perf_counter()
        with torch.no_grad():
            vertices = model(params).vertices[0]
        posing += time.perf_counter() - t
        for K, view in cameras:
            t = time.perf_counter()
            rgb = (renderer.render(vertices, view, K).rgb.numpy() * 255 + 0.5).astype(np.uint8)
            rendering += time.perf_counter() - t
            t = time.perf_counter()
            face_mesh_pixels(detector, rgb)
            detecting += time.perf_counter() - t
print(
    f"per expression: pose {posing / 10 * 1e3:.0f} ms; "
    f"per view: render {rendering / 30 * 1e3:.0f} ms, detect {detecting / 30 * 1e3:.0f} ms"
)
