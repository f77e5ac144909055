"""Anny's painted face with random expressions (``build_calibration``'s sampler), each from three
views, MediaPipe on each render; saves the actions, what the detector read beyond the projected
correspondence points (face-frame units) and the view.

    python renders.py N SEED OUT.npz [random]

Without ``random`` the three views are ``build_calibration``'s fixed ones (the tree at 2879ef3)
and the view saved is its index; with it, yaw U(-40, 40) and pitch U(-20, 20) degrees per render
and the camera's direction in the face's keypoint frame (x right iris to left, y eyes to nose
tip made orthogonal to x) is saved."""

import sys
import time
from contextlib import ExitStack

import numpy as np
import torch
from mediapipe.python.solutions import face_mesh as mp_face_mesh

from eva_engine.align.face_calibration import VIEWS_DEG, in_face_frame, random_expressions
from eva_engine.align.face_mesh import (
    face_mesh_pixels,
    head_camera,
    load_correspondence,
    painted_face_renderer,
)
from eva_engine.body import load_body_model
from eva_engine.geometry import project_points, to_camera

torch.set_num_threads(1)
model = load_body_model("anny")
reg, landmarks = load_correspondence(model).regressor(model)
lm = landmarks.numpy()
names = list(model.expression_names)
kn = list(model.keypoint_names)
frame = [kn.index(n) for n in ("face_right_iris", "face_left_iris", "face_nose_tip")]


def camera_direction(points: np.ndarray) -> np.ndarray:
    right, left, nose = points
    x = (left - right) / np.linalg.norm(left - right)
    y = nose - 0.5 * (left + right)
    y = y - (y @ x) * x
    y = y / np.linalg.norm(y)
    d = -nose / np.linalg.norm(nose)
    return np.array([d @ x, d @ y, d @ np.cross(x, y)])


n, seed, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
random_views = len(sys.argv) > 4 and sys.argv[4] == "random"
rng = np.random.default_rng(seed + 100)
expressions = random_expressions(names, n, np.random.default_rng(seed))
features, readings, views = [], [], []
t0 = time.time()
with (
    ExitStack() as stack,
    mp_face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True) as detector,
):
    renderer = stack.enter_context(painted_face_renderer(model, 512))
    for e in expressions:
        params = model.default_params(1)
        params.expression[0] = torch.from_numpy(e).to(params.expression)
        with torch.no_grad():
            vertices = model(params).vertices[0]
            points = model.posed_points(params, reg)[0].double()
            keypoints = model.posed_keypoints(params)[0][0, frame].double()
        for v in range(3):
            yaw, pitch = (rng.uniform(-40, 40), rng.uniform(-20, 20)) if random_views else VIEWS_DEG[v]
            K, view = head_camera(model, yaw, pitch, 512)
            rgb = (renderer.render(vertices, view, K).rgb.numpy() * 255 + 0.5).astype(np.uint8)
            detected = face_mesh_pixels(detector, rgb)
            if detected is None:
                continue
            uv = project_points(to_camera(points[None], view[None].double()), K[None].double())[0]
            features.append(e)
            readings.append(in_face_frame(detected[lm] - uv.numpy(), detected))
            seen = to_camera(keypoints[None], view[None].double())[0].numpy()
            views.append(camera_direction(seen) if random_views else np.array([v, 0.0, 0.0]))
print("renders", len(features), f"{time.time() - t0:.0f} s")
np.savez(out, X=np.array(features), R=np.array(readings), D=np.array(views), lms=lm, names=np.array(names))
