"""Diagnostic: how much of MediaPipe's landmark residual on Anny's rendered faces (detected minus
the correspondence point projected) is a linear function of the expression."""

import sys
import time

import numpy as np
import torch
from mediapipe.python.solutions import face_mesh as mp_fm

from eva_engine.align.face_mesh import head_camera, load_correspondence
from eva_engine.body import load_body_model
from eva_engine.geometry import project_points, to_camera
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer
from eva_engine.synth.texture import Look, apply_look

model = load_body_model("anny")
corr = load_correspondence(model)
reg, lms = corr.regressor(model)
names = model.expression_names
E = len(names)
rng = np.random.default_rng(0)
N = int(sys.argv[1]) if len(sys.argv) > 1 else 200
views = [(0.0, 0.0), (-15.0, 5.0), (15.0, -5.0)]
exprs = np.zeros((N, E))
for i in range(N):
    for j in rng.choice(E, size=rng.integers(1, 5), replace=False):
        exprs[i, j] = rng.uniform(0.2, 1.0)
    if rng.random() < 0.3:
        b = rng.uniform(0.3, 1.0)
        exprs[i, names.index("eyeBlinkLeft")] = b
        exprs[i, names.index("eyeBlinkRight")] = b
exprs[0] = 0
params0 = model.default_params(1)
look = Look.random(np.random.default_rng([0, 1]))
cfg = MeshRenderConfig(width=512, height=512, supersample=2)
X, R, V = [], [], []
t0 = time.time()
with (
    MeshRenderer(model.faces, cfg, num_vertices=model.num_vertices) as renderer,
    mp_fm.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True) as fm,
):
    apply_look(renderer, model, params0, look, 2048)
    for i in range(N):
        p = model.default_params(1)
        p.expression[0] = torch.from_numpy(exprs[i]).to(p.expression)
        with torch.no_grad():
            verts = model(p).vertices[0]
            pts3 = model.posed_points(p, reg)[0]
        for vi, (yaw, pitch) in enumerate(views):
            K, view = head_camera(model, yaw, pitch, 512)
            r = renderer.render(verts, view, K)
            rgb = (r.rgb.numpy() * 255 + 0.5).astype(np.uint8)
            res = fm.process(np.ascontiguousarray(rgb))
            if not res.multi_face_landmarks:
                continue
            det = np.array([(q.x * 512, q.y * 512) for q in res.multi_face_landmarks[0].landmark])
            uv = project_points(to_camera(pts3[None].double(), view[None].double()), K[None].double())[
                0
            ].numpy()
            d = det[lms.numpy()]
            # face frame from the detection: eye corners 33 (right), 263 (left)
            a, b = det[33], det[263]
            s = np.linalg.norm(b - a)
            ex = (b - a) / s
            ey = np.array([-ex[1], ex[0]])
            res2 = (d - uv) / s
            local = np.stack([res2 @ ex, res2 @ ey], -1)
            X.append(exprs[i])
            R.append(local)
            V.append(vi)
print("renders+detect", time.time() - t0, "s", len(X))
X, R, V = np.array(X), np.array(R), np.array(V)
np.savez(sys.argv[2] if len(sys.argv) > 2 else "calib_diag.npz", X=X, R=R, V=V, lms=lms.numpy())
n = len(X)
idx = rng.permutation(n)
tr, te = idx[: int(0.7 * n)], idx[int(0.7 * n) :]
A = np.concatenate([np.ones((n, 1)), X], 1)
Y = R.reshape(n, -1)
lam = 1e-2
W = np.linalg.solve(A[tr].T @ A[tr] + lam * np.eye(A.shape[1]), A[tr].T @ Y[tr])
pred = A[te] @ W


def rms(x):
    return float(np.sqrt((x**2).mean()))


print(
    "test RMS residual (eye-corner units): raw",
    rms(Y[te]),
    "minus mean",
    rms(Y[te] - Y[tr].mean(0)),
    "linear",
    rms(Y[te] - pred),
)
# per group
L = len(lms)
lm = lms.numpy()
groups = {
    "lids": [159, 145, 386, 374, 160, 144, 158, 153, 385, 380, 387, 373],
    "inner lips": [13, 14, 81, 178, 82, 87, 312, 317, 311, 402],
    "brows": [105, 66, 334, 296, 107, 336, 70, 300, 63, 293],
}
for g, ks in groups.items():
    cols = [np.where(lm == k)[0][0] for k in ks if k in lm]
    Yt = Y[te].reshape(-1, L, 2)[:, cols]
    Pt = pred.reshape(-1, L, 2)[:, cols]
    Mt = Y[tr].reshape(-1, L, 2)[:, cols].mean(0)
    print(g, "raw", rms(Yt), "mean", rms(Yt - Mt), "linear", rms(Yt - Pt))
