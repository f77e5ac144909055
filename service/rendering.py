"""Loaded avatars and what the render and export endpoints do with them: render through
``Avatar.render`` (the request's pose, camera and size: ``eva_engine.avatar.render_spec``), encode
PNG/JPEG, and write the posed body mesh as GLB."""

from __future__ import annotations

import io
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from eva_engine.avatar import Avatar, load_avatar
from eva_engine.avatar.frames import AvatarFrames, load_avatar_frames
from eva_engine.avatar.render_spec import render_image as _render_image
from eva_engine.body import BodyModel, BodyParams, load_body_model
from eva_engine.render.camera import Camera
from eva_engine.render.sh import SH_C0


@dataclass
class LoadedAvatar:
    avatar: Avatar
    frames: AvatarFrames | None
    lock: threading.Lock


class AvatarCache:
    """Up to ``capacity`` avatars kept loaded (LRU), and one body model per name (loaded once)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._avatars: OrderedDict[tuple[str, float], LoadedAvatar] = OrderedDict()
        self._bodies: dict[str, BodyModel] = {}
        self._lock = threading.Lock()

    def body(self, name: str) -> BodyModel:
        with self._lock:
            if name not in self._bodies:
                self._bodies[name] = load_body_model(name)
            return self._bodies[name]

    def get(self, avatar_id: str, path: Path) -> LoadedAvatar:
        key = (avatar_id, path.stat().st_mtime)
        with self._lock:
            if key in self._avatars:
                self._avatars.move_to_end(key)
                return self._avatars[key]
        from eva_engine.avatar import read_avatar_info

        body = self.body(read_avatar_info(path)["body_model"])
        loaded = LoadedAvatar(load_avatar(path, body=body).eval(), load_avatar_frames(path), threading.Lock())
        with self._lock:
            self._avatars[key] = loaded
            while len(self._avatars) > self.capacity:
                self._avatars.popitem(last=False)
        return loaded

    def forget(self, avatar_id: str) -> None:
        with self._lock:
            for key in [k for k in self._avatars if k[0] == avatar_id]:
                del self._avatars[key]


# -- render (pose, camera and size come from eva_engine.avatar.render_spec) ------------------------
def render_image(loaded: LoadedAvatar, params: BodyParams, camera: Camera, background) -> np.ndarray:
    """[H, W, 3] uint8 (one render at a time per loaded avatar)."""
    with loaded.lock:
        return _render_image(loaded.avatar, params, camera, background)


def encode_image(image: np.ndarray, fmt: str) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    if fmt == "png":
        Image.fromarray(image).save(buf, format="PNG")
    else:
        Image.fromarray(image).save(buf, format="JPEG", quality=92)
    return buf.getvalue()


# -- export ----------------------------------------------------------------------------------------
def posed_mesh_glb(loaded: LoadedAvatar, params: BodyParams) -> bytes:
    """The avatar's body mesh in ``params``'s pose (the avatar's own shape), coloured per vertex by
    the mean base colour of the Gaussians attached to it, as binary glTF."""
    import trimesh

    avatar = loaded.avatar
    with loaded.lock, torch.no_grad():
        vertices = avatar.body(avatar.subject_params(params)).vertices[0].cpu().numpy()
        g = avatar.gaussians
        rgb = (0.5 + SH_C0 * g.splats["sh0"].reshape(-1, 3)).clamp(0.0, 1.0)
        n = vertices.shape[0]
        total = torch.zeros(n, 3).index_add_(0, g.vertex_ids.cpu(), rgb.cpu().float())
        count = torch.zeros(n).index_add_(0, g.vertex_ids.cpu(), torch.ones(len(rgb)))
        mean = total / count.clamp_min(1.0)[:, None]
        colors = torch.where(count[:, None] > 0, mean, torch.full((n, 3), 0.7))
    faces = avatar.body.faces.cpu().numpy()
    rgba = np.concatenate([(colors.numpy() * 255 + 0.5).astype(np.uint8), np.full((n, 1), 255, np.uint8)], 1)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=rgba, process=False)
    return mesh.export(file_type="glb")


def rest_params(loaded: LoadedAvatar) -> BodyParams:
    return loaded.avatar.body.default_params(1)
