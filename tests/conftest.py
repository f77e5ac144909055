"""Shared fixtures: body models built once per test session, and a generated SMPL-X-format file.

SMPL-X's files are licensed, so ``make_smplx_npz`` writes a stand-in with the same keys, dtypes
and array conventions as ``SMPLX_NEUTRAL.npz`` (v1.0 layout: 10 betas + 10 expression
directions, 486 pose directions, 55 joints, 51 static + 79x17 dynamic face landmarks) and the
real vertex count (smplx's own forward selects extra joints by fixed vertex ids), but made-up
geometry: a stick figure whose vertices sit around the joints they are skinned to.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

SMPLX_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15]
SMPLX_PARENTS += [20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38]
SMPLX_PARENTS += [21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53]
SMPLX_NUM_VERTICES = 10475


def _smplx_joint_positions() -> np.ndarray:
    """A rough adult skeleton in SMPL-X joint order (Y up, facing +Z, +X = subject's left)."""
    left = {
        "hip": (0.09, -0.08, 0.0),
        "knee": (0.1, -0.48, 0.0),
        "ankle": (0.1, -0.88, -0.02),
        "foot": (0.1, -0.93, 0.1),
        "collar": (0.07, 0.42, 0.0),
        "shoulder": (0.17, 0.45, 0.0),
        "elbow": (0.42, 0.45, 0.0),
        "wrist": (0.67, 0.45, 0.0),
        "eye": (0.03, 0.68, 0.08),
    }
    fingers = {  # name: (first joint offset from wrist, direction)
        "index": ((0.09, 0.0, 0.03), (1.0, 0.0, 0.0)),
        "middle": ((0.095, 0.0, 0.01), (1.0, 0.0, 0.0)),
        "pinky": ((0.08, 0.0, -0.04), (1.0, 0.0, 0.0)),
        "ring": ((0.09, 0.0, -0.015), (1.0, 0.0, 0.0)),
        "thumb": ((0.03, -0.01, 0.04), (0.6, -0.2, 0.7)),
    }
    pos = {
        "pelvis": (0.0, 0.0, 0.0),
        "spine1": (0.0, 0.1, 0.0),
        "spine2": (0.0, 0.22, 0.0),
        "spine3": (0.0, 0.28, 0.0),
        "neck": (0.0, 0.5, 0.0),
        "head": (0.0, 0.62, 0.02),
        "jaw": (0.0, 0.6, 0.05),
    }
    for side, sign in (("left", 1.0), ("right", -1.0)):
        for name, p in left.items():
            key = f"{side}_{name}_smplhf" if name == "eye" else f"{side}_{name}"
            pos[key] = (sign * p[0], p[1], p[2])
        wrist = np.array(pos[f"{side}_wrist"])
        for finger, (offset, direction) in fingers.items():
            d = np.array(direction) / np.linalg.norm(direction)
            base = wrist + np.array(offset) * (sign, 1.0, 1.0)
            for k in range(3):
                p = base + 0.03 * k * d * (sign, 1.0, 1.0)
                pos[f"{side}_{finger}{k + 1}"] = tuple(p)
    from smplx.joint_names import JOINT_NAMES

    return np.array([pos[n] for n in JOINT_NAMES[:55]], dtype=np.float64)


def make_smplx_npz(path: Path, seed: int = 0) -> Path:
    """Write a SMPL-X-format ``.npz`` (see the module docstring) and return its path."""
    rng = np.random.default_rng(seed)
    joints = _smplx_joint_positions()
    n_joints = len(joints)
    parents = np.array(SMPLX_PARENTS)
    children = {j: [c for c in range(n_joints) if parents[c] == j] for j in range(n_joints)}
    # Roughly SMPL-X's proportions: ~12% hands, ~20% head.
    per_joint = np.full(n_joints, 360)
    per_joint[25:] = 40  # finger joints
    per_joint[[20, 21]] = 150  # wrists (palms)
    per_joint[15], per_joint[22], per_joint[[23, 24]] = 1500, 300, 100  # head, jaw, eyes
    per_joint[0] += SMPLX_NUM_VERTICES - per_joint.sum()
    finger = np.arange(n_joints) >= 25
    radius = np.where(finger, 0.008, 0.04)
    radius[[15, 22]] = 0.07  # head, jaw
    radius[[23, 24]] = 0.012  # eyes

    vertices, weights, faces, regressor = [], [], [], np.zeros((n_joints, SMPLX_NUM_VERTICES))
    start = 0
    ring = 8
    for j in range(n_joints):
        n = int(per_joint[j])
        end_point = (
            joints[children[j]].mean(axis=0)
            if children[j]
            else joints[j] + (joints[j] - joints[max(parents[j], 0)]) * 0.3
        )
        t = np.concatenate([np.zeros(ring), rng.uniform(0.0, 1.0, n - ring)])
        angle = np.concatenate(
            [np.linspace(0, 2 * np.pi, ring, endpoint=False), rng.uniform(0, 2 * np.pi, n - ring)]
        )
        axis = end_point - joints[j]
        axis = axis / (np.linalg.norm(axis) + 1e-12) if np.linalg.norm(axis) > 1e-9 else np.array([0, 1.0, 0])
        u = np.cross(axis, [0.3, 0.5, 0.8])
        u /= np.linalg.norm(u)
        w = np.cross(axis, u)
        centre = joints[j] + t[:, None] * (end_point - joints[j])
        v = centre + radius[j] * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * w)
        vertices.append(v)
        regressor[j, start : start + ring] = 1.0 / ring  # ring centred on the joint
        wv = np.zeros((n, n_joints))
        if parents[j] < 0:
            wv[:, j] = 1.0
        else:
            wv[:, j] = 0.5 + 0.5 * t
            wv[:, parents[j]] = 0.5 - 0.5 * t
        weights.append(wv)
        idx = start + np.arange(n)
        faces.append(np.stack([idx[:-2], idx[1:-1], idx[2:]], axis=1))
        start += n
    v_template = np.concatenate(vertices)
    f = np.concatenate(faces).astype(np.uint32)
    head_faces = np.nonzero(((f >= per_joint[:15].sum()) & (f < per_joint[:16].sum())).all(axis=1))[0]

    def bary(*shape):
        b = rng.uniform(0.1, 1.0, (*shape, 3))
        return b / b.sum(-1, keepdims=True)

    posedirs = np.zeros((SMPLX_NUM_VERTICES, 3, 486))
    posedirs[:400] = rng.normal(0.0, 1e-3, (400, 3, 486))  # sparse, so the file compresses
    kintree = np.stack([parents, np.arange(n_joints)]).astype(np.int64)
    kintree[0, 0] = 4294967295  # the real files store the root's parent as uint32(-1)
    hands = {}
    for side in "lr":
        q, _ = np.linalg.qr(rng.normal(size=(45, 45)))
        hands[f"hands_components{side}"] = q
        hands[f"hands_mean{side}"] = rng.normal(0.0, 0.1, 45)
    np.savez_compressed(
        path,
        v_template=v_template,
        f=f,
        shapedirs=rng.normal(0.0, 0.01, (SMPLX_NUM_VERTICES, 3, 20)),
        posedirs=posedirs,
        J_regressor=regressor,
        kintree_table=kintree,
        weights=np.concatenate(weights),
        lmk_faces_idx=rng.choice(head_faces, 51).astype(np.uint32),
        lmk_bary_coords=bary(51),
        dynamic_lmk_faces_idx=rng.choice(head_faces, (79, 17)).astype(np.int32),
        dynamic_lmk_bary_coords=bary(79, 17),
        **hands,
    )
    return Path(path)


@pytest.fixture(scope="session")
def anny_model():
    """The Anny body model, loaded once per session (its cache is built by `eva setup`)."""
    from eva_engine.body import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="session")
def smplx_dir(tmp_path_factory) -> Path:
    """A folder holding a generated ``SMPLX_NEUTRAL.npz``."""
    folder = tmp_path_factory.mktemp("smplx")
    make_smplx_npz(folder / "SMPLX_NEUTRAL.npz")
    return folder


@pytest.fixture(scope="session")
def smplx_model(smplx_dir):
    from eva_engine.body import load_body_model

    return load_body_model("smplx", model_path=smplx_dir)


@pytest.fixture(scope="session")
def body_models(anny_model, smplx_model) -> dict:
    return {"anny": anny_model, "smplx": smplx_model}


@pytest.fixture
def torch_seed():
    torch.manual_seed(0)


@pytest.fixture(autouse=True)
def wide_terminal(monkeypatch):
    """CLI errors are drawn in rich boxes as wide as the terminal (80 columns here): a long
    temporary path would otherwise break the phrase a test looks for across two lines."""
    monkeypatch.setenv("COLUMNS", "400")
