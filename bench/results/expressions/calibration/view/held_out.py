"""Held-out RMS of what the detector reads beyond the correspondence points (eye-corner units),
before and after a ridge regression on the actions alone (``lin``, the calibration's model at
2879ef3) and on the actions plus polynomial terms of the view:

    python held_out.py TRAIN.npz TEST.npz            # both from renders.py ... random
    python held_out.py TRAIN.npz TEST.npz THREE.npz  # also by yaw band, THREE from the fixed views
"""

import sys

import numpy as np
from mediapipe.python.solutions import face_mesh_connections as fmc

train, test = np.load(sys.argv[1]), np.load(sys.argv[2])
lms = train["lms"]


def members(*connections) -> np.ndarray:
    return np.isin(lms, [i for c in connections for pair in c for i in pair])


regions = {
    "all": np.ones(len(lms), bool),
    "eyes": members(fmc.FACEMESH_LEFT_EYE, fmc.FACEMESH_RIGHT_EYE),
    "lips": members(fmc.FACEMESH_LIPS),
    "brows": members(fmc.FACEMESH_LEFT_EYEBROW, fmc.FACEMESH_RIGHT_EYEBROW),
}
FRONTAL = np.array([0.0, 0.5535])  # the rest face's direction seen head on


def features(x: np.ndarray, d: np.ndarray, kind: str) -> np.ndarray:
    u, v = (d[:, 0] - FRONTAL[0])[:, None], (d[:, 1] - FRONTAL[1])[:, None]
    cols = [np.ones((len(x), 1)), x]
    if kind in ("v1", "v2", "v3", "v3+int"):
        cols += [u, v]
    if kind in ("v2", "v3", "v3+int"):
        cols += [u * u, v * v, u * v]
    if kind in ("v3", "v3+int"):
        cols += [u**3, v**3, u * u * v, u * v * v]
    if kind == "v3+int":
        cols += [x * u, x * v]
    return np.concatenate(cols, 1)


def ridge(a: np.ndarray, y: np.ndarray, lam: float = 1e-2) -> np.ndarray:
    return np.linalg.solve(a.T @ a + lam * np.eye(a.shape[1]), a.T @ y.reshape(len(y), -1))


def rms(r: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt((r[:, mask] ** 2).mean()))


print("| model | " + " | ".join(regions) + " |\n|---|" + "---:|" * len(regions))
print("| none | " + " | ".join(f"{rms(test['R'], m):.4f}" for m in regions.values()) + " |")
for kind in ("lin", "v1", "v2", "v3", "v3+int"):
    w = ridge(features(train["X"], train["D"], kind), train["R"])
    res = test["R"] - (features(test["X"], test["D"], kind) @ w).reshape(test["R"].shape)
    print(f"| {kind} | " + " | ".join(f"{rms(res, m):.4f}" for m in regions.values()) + " |")

if len(sys.argv) > 3:  # the calibration at 2879ef3 (three fixed views, actions only) against v3, by yaw
    three = np.load(sys.argv[3])
    w_three = ridge(features(three["X"], three["D"], "lin"), three["R"])
    w_view = ridge(features(train["X"], train["D"], "v3"), train["R"])
    yaw = np.degrees(np.arcsin(np.clip(test["D"][:, 0], -1, 1)))
    print("\n| abs(yaw), deg | renders | none | three fixed views, actions | random views, actions + v3 |")
    print("|---|---:|---:|---:|---:|")
    for lo, hi in ((0, 10), (10, 20), (20, 30), (30, 45)):
        m = (np.abs(yaw) >= lo) & (np.abs(yaw) < hi)
        y = test["R"][m]
        r_three = y - (features(test["X"][m], test["D"][m], "lin") @ w_three).reshape(y.shape)
        r_view = y - (features(test["X"][m], test["D"][m], "v3") @ w_view).reshape(y.shape)
        cells = [rms(q, regions["all"]) for q in (y, r_three, r_view)]
        print(f"| {lo}-{hi} | {m.sum()} | " + " | ".join(f"{c:.4f}" for c in cells) + " |")
