"""The training frames kept with an avatar: each frame's fitted body parameters and camera, so the
avatar can be rendered in a training frame's pose and view to compare with the input video (the
render endpoint's ``frame``, ``eva render --pose frame:N``).

``frames.safetensors`` in the avatar directory holds ``params.<name>`` (``BodyParams`` fields,
batch F), ``K [F, 3, 3]``, ``viewmat [F, 4, 4]`` and ``timestamps [F]``; ``avatar.json``'s
``frames`` entry holds ``count``, ``image_size`` (height, width) and ``fps``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from eva_engine.body.params import BodyParams

FRAMES_NAME = "frames.safetensors"


@dataclass
class AvatarFrames:
    """params: the frames' fitted ``BodyParams`` (batch F); K [F, 3, 3]; viewmat [F, 4, 4];
    size: image (height, width) in pixels, (0, 0) when unknown."""

    params: BodyParams
    K: torch.Tensor
    viewmat: torch.Tensor
    size: tuple[int, int]

    def __len__(self) -> int:
        return self.params.batch_size


def save_avatar_frames(folder: str | Path, dataset, params: BodyParams | None = None) -> dict:
    """Write ``dataset``'s (an ``eva_engine.data.Dataset`` with params) frames into the avatar
    directory ``folder``, with ``params`` (batch F; e.g. ``TrainResult.frame_params``: the fits
    as trained, pose-corrected) in place of the dataset's own fits when given; returns the
    ``frames`` entry for ``avatar.json``."""
    from safetensors.torch import save_file

    params = params if params is not None else dataset.params
    if params is None:
        raise ValueError("the dataset has no body parameters to keep with the avatar")
    if params.batch_size != len(dataset.timestamps):
        raise ValueError(f"{params.batch_size} frame params for {len(dataset.timestamps)} frames")
    tensors = {f"params.{k}": v.detach().cpu().float().contiguous() for k, v in params.tensors().items()}
    tensors["K"] = dataset.K.float().contiguous()
    tensors["viewmat"] = dataset.viewmat.float().contiguous()
    tensors["timestamps"] = torch.as_tensor(dataset.timestamps, dtype=torch.float64)
    save_file(tensors, str(Path(folder) / FRAMES_NAME))
    meta = dataset.meta
    return {"count": params.batch_size, "image_size": list(meta.image_size), "fps": meta.fps}


def load_avatar_frames(folder: str | Path) -> AvatarFrames | None:
    """The training frames kept in the avatar directory ``folder`` (None if it keeps none)."""
    from safetensors.torch import load_file

    from eva_engine.avatar.io import read_avatar_info

    file = Path(folder) / FRAMES_NAME
    if not file.is_file():
        return None
    t = load_file(str(file))
    params = BodyParams(**{k.removeprefix("params."): v for k, v in t.items() if k.startswith("params.")})
    h, w = read_avatar_info(folder).get("frames", {}).get("image_size", (0, 0))
    return AvatarFrames(params, t["K"], t["viewmat"], (int(h), int(w)))
