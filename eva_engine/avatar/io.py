"""The avatar directory, one artefact read and written here: an avatar directory holds

- ``avatar.ply``: the canonical Gaussians in the standard 3DGS PLY layout (x, y, z, nx, ny, nz,
  f_dc_0..2, f_rest_0..3(K-1)-1 channel-major, opacity (logit), scale_0..2 (log), rot_0..3
  (w, x, y, z)), so common splat viewers open it (in the rest pose);
- ``avatar.safetensors``: what the PLY does not hold: the MLP weights, per-Gaussian part ids and
  template vertex ids, the body-model identity (name in the metadata, ``shape`` tensor), and with
  ``AvatarConfig.expression_colours`` the colour offsets per expression action
  (``splats.sh0_expression [N, A, 3]``, A actions) and their scale (``expression_range [A]``),
  and the template's expression where it is not zero (``template_expression [E]``);
- ``frames.safetensors`` (optional): the training frames (:class:`AvatarFrames`):
  ``params.<name>`` (``BodyParams`` fields, batch F), ``K [F, 3, 3]``, ``viewmat [F, 4, 4]`` and
  ``timestamps [F]``;
- ``avatar.json``: :class:`AvatarMeta`: the format, the body model, the avatar config, the Gaussian
  count, the training frames' count, size and rate, and how the avatar was made
  (:class:`TrainingRecord`: training config and time, metrics, where the data came from, and the
  views and poses training showed: ``coverage``).

No pickle anywhere. ``load_avatar(path)`` rebuilds an :class:`Avatar` ready to ``render``;
``load_saved_avatar(path)`` reads the whole directory (:class:`SavedAvatar`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from safetensors.torch import load_file, save_file

from eva_engine.avatar.config import AvatarConfig
from eva_engine.avatar.coverage import Coverage
from eva_engine.avatar.frames import AvatarFrames
from eva_engine.avatar.gaussians import OPTIONAL_SPLAT_NAMES, CanonicalGaussians
from eva_engine.avatar.model import Avatar, template_vertices
from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams

FORMAT = "eva-avatar"
VERSION = 1
PLY_NAME, TENSORS_NAME, JSON_NAME = "avatar.ply", "avatar.safetensors", "avatar.json"
FRAMES_NAME = "frames.safetensors"


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
        ("x", means[:, 0]),
        ("y", means[:, 1]),
        ("z", means[:, 2]),
        ("nx", np.zeros(n)),
        ("ny", np.zeros(n)),
        ("nz", np.zeros(n)),
    ]
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


# -- avatar.json -----------------------------------------------------------------------------------
class FramesInfo(BaseModel):
    """``avatar.json``'s summary of the training frames (readable without loading them)."""

    count: int
    image_size: tuple[int, int]
    """(height, width) in pixels."""
    fps: float

    @classmethod
    def of(cls, frames: AvatarFrames) -> FramesInfo:
        return cls(count=len(frames), image_size=frames.image_size, fps=frames.fps)


class TrainingRecord(BaseModel):
    """How an avatar was made, as ``avatar.json`` keeps it; every field is optional. The training
    run (``TrainResult.record``), the fit on training frames (``metrics``: psnr, ssim, lpips_vgg,
    lpips_alex, ...), the quality report (``quality``: held-out frames and detection) and where
    the data came from (a dataset folder, or a job of the service)."""

    model_config = ConfigDict(extra="forbid")

    preset: str | None = None
    method: str | None = None
    train_config: dict[str, Any] | None = None
    iterations: int | None = None
    train_seconds: float | None = None
    final_loss: float | None = None
    timings: dict[str, float] = Field(default_factory=dict)
    refinements: list[dict[str, Any]] = Field(default_factory=list)
    gaussians_per_part: dict[str, dict[str, int]] = Field(default_factory=dict)
    pose_correction: dict[str, float] = Field(default_factory=dict)
    coverage: Coverage | None = None
    """The views and poses the training frames showed (``avatar.coverage``)."""
    metrics: dict[str, Any] = Field(default_factory=dict)
    quality: dict[str, Any] | None = None
    """``eval.QualityReport``: held-out scores and what preprocessing saw (None: not measured)."""
    dataset: str | None = None
    source_video: str | None = None
    avatar_id: str | None = None
    job_id: str | None = None
    options: dict[str, Any] | None = None
    created_at: float | None = None


class AvatarMeta(TrainingRecord):
    """``avatar.json``: the format, what the model files hold (body model, Gaussian count, avatar
    config, active SH degree), the training frames' summary (None: the avatar keeps none), and
    the :class:`TrainingRecord`. Keys it does not know (a newer writer's) are ignored."""

    model_config = ConfigDict(extra="ignore")

    format: Literal["eva-avatar"] = FORMAT
    version: int = VERSION
    body_model: str
    num_gaussians: int
    active_sh_degree: int | None = None
    """None in files that did not record it: the Gaussians' full SH degree."""
    avatar_config: dict[str, Any]
    frames: FramesInfo | None = None


def _directory(path: str | Path) -> Path:
    root = Path(path)
    if not root.is_dir():
        raise AvatarFileError(f"no avatar directory at {root}")
    return root


def read_avatar_meta(path: str | Path) -> AvatarMeta:
    """The ``avatar.json`` of the avatar directory ``path``."""
    root = _directory(path)
    file = root / JSON_NAME
    if not file.is_file():
        raise AvatarFileError(f"{root} is not an avatar directory: no {JSON_NAME}")
    try:
        doc = json.loads(file.read_text())
    except json.JSONDecodeError as err:
        raise AvatarFileError(f"{file} is not valid JSON: {err}") from err
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else None
        raise AvatarFileError(f"{file}: format is {found!r}, expected {FORMAT!r}")
    if int(doc.get("version", 0)) > VERSION:
        raise AvatarFileError(f"{file}: version {doc['version']} is newer than this reader ({VERSION})")
    try:  # null is absent: older writers wrote None for what they did not know
        return AvatarMeta.model_validate({k: v for k, v in doc.items() if v is not None})
    except ValidationError as err:
        raise AvatarFileError(f"{file} is malformed: {err}") from err


# -- saving ----------------------------------------------------------------------------------------
def save_avatar(
    avatar: Avatar,
    path: str | Path,
    record: TrainingRecord | None = None,
    frames: AvatarFrames | None = None,
) -> Path:
    """Write ``avatar`` to the directory ``path`` (created; files inside are replaced), with how it
    was made (``record``) and its training frames (``frames``, None: keeps none)."""
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    g = avatar.gaussians
    write_ply(root / PLY_NAME, dict(g.splats.items()))
    tensors = {"shape": avatar.shape, "part_ids": g.part_ids, "vertex_ids": g.vertex_ids}
    for name in OPTIONAL_SPLAT_NAMES:  # not in the 3DGS PLY layout: kept with the other tensors
        if name in g.splats:
            tensors[f"splats.{name}"] = g.splats[name]
    if avatar.config.expression_colours:
        tensors["expression_range"] = avatar.expression_range
    if bool(avatar.template_expression.any()):
        tensors["template_expression"] = avatar.template_expression
    for prefix, module in avatar.networks().items():
        tensors.update({f"{prefix}.{k}": v for k, v in module.state_dict().items()})
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    metadata = {
        "format": FORMAT,
        "version": str(VERSION),
        "body_model": avatar.body.name,
        "shape_names": json.dumps(list(avatar.body.shape_names)),
    }
    save_file(tensors, str(root / TENSORS_NAME), metadata=metadata)
    if frames is not None:
        _save_frames(root / FRAMES_NAME, frames)
    else:
        (root / FRAMES_NAME).unlink(missing_ok=True)
    meta = AvatarMeta(
        **(record or TrainingRecord()).model_dump(),
        body_model=avatar.body.name,
        num_gaussians=len(g),
        active_sh_degree=avatar.active_sh_degree,
        avatar_config=avatar.config.to_dict(),
        frames=FramesInfo.of(frames) if frames is not None else None,
    )
    (root / JSON_NAME).write_text(meta.model_dump_json(indent=2, exclude_none=True))
    return root


def _save_frames(file: Path, frames: AvatarFrames) -> None:
    tensors = {f"params.{k}": v.float() for k, v in frames.params.tensors().items()}
    tensors |= {"K": frames.K.float(), "viewmat": frames.viewmat.float()}
    tensors["timestamps"] = frames.timestamps.double()
    save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(file))


# -- loading ---------------------------------------------------------------------------------------
@dataclass
class SavedAvatar:
    """A whole avatar directory: the model (ready to render), its ``avatar.json`` and its training
    frames (None when it keeps none)."""

    avatar: Avatar
    meta: AvatarMeta
    frames: AvatarFrames | None


def load_avatar_frames(path: str | Path, meta: AvatarMeta | None = None) -> AvatarFrames | None:
    """The training frames kept in the avatar directory ``path`` (None if it keeps none).
    ``meta``: its ``avatar.json``, when already read."""
    root = _directory(path)
    file = root / FRAMES_NAME
    if not file.is_file():
        return None
    meta = meta or read_avatar_meta(root)
    try:
        t = load_file(str(file))
        params = BodyParams(**{k.removeprefix("params."): v for k, v in t.items() if k.startswith("params.")})
        K, viewmat = t["K"], t["viewmat"]
    except Exception as err:  # safetensors and BodyParams raise several types for bad files
        raise AvatarFileError(f"cannot read {file}: {err}") from err
    info = meta.frames
    return AvatarFrames(
        params=params,
        K=K,
        viewmat=viewmat,
        timestamps=t.get("timestamps", torch.zeros(params.batch_size, dtype=torch.float64)),
        image_size=info.image_size if info else (0, 0),
        fps=info.fps if info else 0.0,
    )


def load_avatar(
    path: str | Path, body: BodyModel | None = None, device: torch.device | str = "cpu"
) -> Avatar:
    """Rebuild the :class:`Avatar` saved in directory ``path``.

    body: the body model to drive it (default: ``load_body_model(<saved name>)``); it must be the
    saved one (same name and shape parameters).
    """
    return _load_model(Path(path), read_avatar_meta(path), body, device)


def load_saved_avatar(
    path: str | Path, body: BodyModel | None = None, device: torch.device | str = "cpu"
) -> SavedAvatar:
    """The whole avatar directory ``path`` (``body`` and ``device`` as in :func:`load_avatar`)."""
    meta = read_avatar_meta(path)
    avatar = _load_model(Path(path), meta, body, device)
    return SavedAvatar(avatar, meta, load_avatar_frames(path, meta))


def _load_model(root: Path, meta: AvatarMeta, body: BodyModel | None, device: torch.device | str) -> Avatar:
    for name in (PLY_NAME, TENSORS_NAME):
        if not (root / name).is_file():
            raise AvatarFileError(f"{root} is incomplete: no {name}")
    if body is None:
        from eva_engine.body import load_body_model

        body = load_body_model(meta.body_model)
    if body.name != meta.body_model:
        raise AvatarFileError(f"avatar was trained with body model {meta.body_model!r}, got {body.name!r}")
    try:
        tensors = load_file(str(root / TENSORS_NAME))
    except Exception as err:
        raise AvatarFileError(f"cannot read {root / TENSORS_NAME}: {err}") from err
    shape = tensors["shape"]
    if shape.shape[0] != len(body.shape_names):
        raise AvatarFileError(f"saved shape has {shape.shape[0]} values, body model {len(body.shape_names)}")
    config = AvatarConfig.from_dict(meta.avatar_config)
    splats = read_ply(root / PLY_NAME)
    splats |= {k: tensors[f"splats.{k}"] for k in OPTIONAL_SPLAT_NAMES if f"splats.{k}" in tensors}
    expression = tensors.get("template_expression")  # absent: the zero expression
    if expression is not None and expression.shape[0] != len(body.expression_names):
        raise AvatarFileError(
            f"saved template expression has {expression.shape[0]} values, body model "
            f"{len(body.expression_names)}"
        )
    template = template_vertices(body, shape, expression)
    ids = tensors["part_ids"], tensors["vertex_ids"]
    gaussians = CanonicalGaussians(splats, *ids, template, body.part_ids)
    avatar = Avatar(body, gaussians, shape, config, expression=expression)
    for prefix, module in avatar.networks().items():
        state = {k[len(prefix) + 1 :]: v for k, v in tensors.items() if k.startswith(prefix + ".")}
        module.load_state_dict(state)
    if config.expression_colours and "expression_range" in tensors:
        avatar.expression_range.copy_(tensors["expression_range"])
    sh = meta.active_sh_degree
    avatar.active_sh_degree = sh if sh is not None else gaussians.sh_degree
    return avatar.to(device)
