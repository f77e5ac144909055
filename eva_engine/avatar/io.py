"""Avatar files: an avatar directory holds

- ``avatar.ply``: the canonical Gaussians in the standard 3DGS PLY layout (x, y, z, nx, ny, nz,
  f_dc_0..2, f_rest_0..3(K-1)-1 channel-major, opacity (logit), scale_0..2 (log), rot_0..3
  (w, x, y, z)), so common splat viewers open it (in the rest pose);
- ``avatar.safetensors``: what the PLY does not hold: the MLP weights, per-Gaussian part ids and
  template vertex ids, and the body-model identity (name in the metadata, ``shape`` tensor);
- ``avatar.json``: format, body model, avatar config, training config and time, Gaussian count,
  metrics (free-form dict written by the trainer / evaluator).

No pickle anywhere. ``load_avatar(path)`` rebuilds an :class:`Avatar` ready to ``render``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from safetensors.torch import load_file, save_file

from eva_engine.avatar.config import AvatarConfig
from eva_engine.avatar.gaussians import CanonicalGaussians
from eva_engine.avatar.model import Avatar, template_vertices
from eva_engine.body.model import BodyModel

FORMAT = "eva-avatar"
VERSION = 1
PLY_NAME, TENSORS_NAME, JSON_NAME = "avatar.ply", "avatar.safetensors", "avatar.json"


class AvatarFileError(RuntimeError):
    """An avatar directory is missing, incomplete or not readable."""


# -- PLY -------------------------------------------------------------------------------------------
def write_ply(path: str | Path, splats: dict[str, torch.Tensor]) -> None:
    """Write splats (``CanonicalGaussians.splats`` layout) as a 3DGS PLY."""
    means = splats["means"].detach().cpu().float().numpy()
    n = means.shape[0]
    f_dc = splats["sh0"].detach().cpu().float().reshape(n, 3).numpy()
    # 3DGS stores the rest coefficients channel-major: [N, K-1, 3] -> [N, 3, K-1] -> flat.
    f_rest = splats["shN"].detach().cpu().float().transpose(1, 2).reshape(n, -1).numpy()
    columns = [
        ("x", means[:, 0]), ("y", means[:, 1]), ("z", means[:, 2]),
        ("nx", np.zeros(n)), ("ny", np.zeros(n)), ("nz", np.zeros(n)),
    ]  # fmt: skip
    columns += [(f"f_dc_{i}", f_dc[:, i]) for i in range(3)]
    columns += [(f"f_rest_{i}", f_rest[:, i]) for i in range(f_rest.shape[1])]
    columns += [("opacity", splats["opacities"].detach().cpu().float().numpy())]
    scales = splats["scales"].detach().cpu().float().numpy()
    quats = splats["quats"].detach().cpu().float().numpy()
    columns += [(f"scale_{i}", scales[:, i]) for i in range(3)]
    columns += [(f"rot_{i}", quats[:, i]) for i in range(4)]
    data = np.empty(n, dtype=[(name, "f4") for name, _ in columns])
    for name, values in columns:
        data[name] = values
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))


def read_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY into splats (``means, scales, quats, opacities, sh0, shN``)."""
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as err:  # plyfile raises several types for malformed files
        raise AvatarFileError(f"cannot read {path} as a 3DGS PLY: {err}") from err
    names = {p.name for p in vertex.properties}

    def cols(prefix: str, count: int) -> np.ndarray:
        missing = [f"{prefix}{i}" for i in range(count) if f"{prefix}{i}" not in names]
        if missing:
            raise AvatarFileError(f"{path} lacks PLY properties {missing}")
        if count == 0:  # SH degree 0: no f_rest columns
            return np.zeros((len(vertex.data), 0), np.float32)
        return np.stack([np.asarray(vertex[f"{prefix}{i}"], dtype=np.float32) for i in range(count)], axis=1)

    n_rest = sum(1 for p in names if p.startswith("f_rest_"))
    if n_rest % 3 or int(np.sqrt(n_rest // 3 + 1)) ** 2 != n_rest // 3 + 1:
        raise AvatarFileError(f"{path}: {n_rest} f_rest properties is not 3 ((d + 1)^2 - 1)")
    n = len(vertex.data)
    means = np.stack([np.asarray(vertex[c], dtype=np.float32) for c in "xyz"], axis=1)
    rest = cols("f_rest_", n_rest).reshape(n, 3, n_rest // 3).transpose(0, 2, 1)
    return {
        "means": torch.from_numpy(means),
        "scales": torch.from_numpy(cols("scale_", 3)),
        "quats": torch.from_numpy(cols("rot_", 4)),
        "opacities": torch.from_numpy(np.asarray(vertex["opacity"], dtype=np.float32).copy()),
        "sh0": torch.from_numpy(cols("f_dc_", 3)).reshape(n, 1, 3),
        "shN": torch.from_numpy(np.ascontiguousarray(rest)),
    }


# -- avatar directory ------------------------------------------------------------------------------
def save_avatar(avatar: Avatar, path: str | Path, info: dict | None = None) -> Path:
    """Write ``avatar`` to the directory ``path`` (created; files inside are replaced).

    info: extra JSON for ``avatar.json`` (training config and time, metrics, ...).
    """
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    g = avatar.gaussians
    write_ply(root / PLY_NAME, dict(g.splats.items()))
    tensors = {"shape": avatar.shape, "part_ids": g.part_ids, "vertex_ids": g.vertex_ids}
    for prefix, module in (("weight_offsets", avatar.weight_offsets), ("pose_refiner", avatar.pose_refiner)):
        if module is not None:
            tensors.update({f"{prefix}.{k}": v for k, v in module.state_dict().items()})
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    meta = {
        "format": FORMAT,
        "version": str(VERSION),
        "body_model": avatar.body.name,
        "shape_names": json.dumps(list(avatar.body.shape_names)),
    }
    save_file(tensors, str(root / TENSORS_NAME), metadata=meta)
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "body_model": avatar.body.name,
        "num_gaussians": len(g),
        "active_sh_degree": avatar.active_sh_degree,
        "avatar_config": avatar.config.to_dict(),
        **(info or {}),
    }
    (root / JSON_NAME).write_text(json.dumps(doc, indent=2))
    return root


def read_avatar_info(path: str | Path) -> dict:
    """The ``avatar.json`` of an avatar directory."""
    root = Path(path)
    file = root / JSON_NAME
    if not root.is_dir():
        raise AvatarFileError(f"no avatar directory at {root}")
    if not file.is_file():
        raise AvatarFileError(f"{root} is not an avatar directory: no {JSON_NAME}")
    try:
        doc = json.loads(file.read_text())
    except json.JSONDecodeError as err:
        raise AvatarFileError(f"{file} is not valid JSON: {err}") from err
    if doc.get("format") != FORMAT:
        raise AvatarFileError(f"{file}: format is {doc.get('format')!r}, expected {FORMAT!r}")
    if int(doc.get("version", 0)) > VERSION:
        raise AvatarFileError(f"{file}: version {doc['version']} is newer than this reader ({VERSION})")
    return doc


def load_avatar(
    path: str | Path, body: BodyModel | None = None, device: torch.device | str = "cpu"
) -> Avatar:
    """Rebuild the :class:`Avatar` saved in directory ``path``.

    body: the body model to drive it (default: ``load_body_model(<saved name>)``); it must be the
    saved one (same name and shape parameters).
    """
    root = Path(path)
    doc = read_avatar_info(root)
    for name in (PLY_NAME, TENSORS_NAME):
        if not (root / name).is_file():
            raise AvatarFileError(f"{root} is incomplete: no {name}")
    if body is None:
        from eva_engine.body import load_body_model

        body = load_body_model(doc["body_model"])
    if body.name != doc["body_model"]:
        raise AvatarFileError(f"avatar was trained with body model {doc['body_model']!r}, got {body.name!r}")
    try:
        tensors = load_file(str(root / TENSORS_NAME))
    except Exception as err:
        raise AvatarFileError(f"cannot read {root / TENSORS_NAME}: {err}") from err
    shape = tensors["shape"]
    if shape.shape[0] != len(body.shape_names):
        raise AvatarFileError(f"saved shape has {shape.shape[0]} values, body model {len(body.shape_names)}")
    config = AvatarConfig.from_dict(doc["avatar_config"])
    splats = read_ply(root / PLY_NAME)
    template = template_vertices(body, shape)
    ids = tensors["part_ids"], tensors["vertex_ids"]
    gaussians = CanonicalGaussians(splats, *ids, template, body.part_ids)
    avatar = Avatar(body, gaussians, shape, config)
    for prefix, module in (("weight_offsets", avatar.weight_offsets), ("pose_refiner", avatar.pose_refiner)):
        if module is not None:
            state = {k[len(prefix) + 1 :]: v for k, v in tensors.items() if k.startswith(prefix + ".")}
            module.load_state_dict(state)
    avatar.active_sh_degree = int(doc.get("active_sh_degree", gaussians.sh_degree))
    return avatar.to(device)
