"""Loaded avatars and what the render and export endpoints do with them: check the size against
the limits before the avatar loads, render through ``Avatar.render`` (the request's pose, camera
and size, checked against the body model: ``eva_engine.avatar.render_spec``; at most
``RenderGate.slots`` at once), encode PNG/JPEG, and write the posed body mesh as GLB."""

from __future__ import annotations

import asyncio
import io
import threading
from collections import OrderedDict, deque
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from eva_engine.avatar import Avatar, AvatarFileError, AvatarFrames, load_saved_avatar, read_avatar_meta
from eva_engine.avatar.coverage import Coverage
from eva_engine.avatar.render_spec import RenderInputError, RenderSpec, resolve_size, uses_training_frame
from eva_engine.avatar.render_spec import render_image as _render_image
from eva_engine.body import BodyModel, BodyParams, load_body_model
from eva_engine.render.camera import Camera
from eva_engine.render.sh import SH_C0
from service.png import encode_png


class RenderBusy(Exception):
    """Every render slot is taken and the waiting line is full or did not move in time (503)."""


class RenderGate:
    """At most ``slots`` renders at once; up to ``waiting`` more wait (first come, first served)
    at most ``wait_s`` seconds, in the event loop (not in threads); beyond that ``RenderBusy``."""

    def __init__(self, slots: int, waiting: int, wait_s: float) -> None:
        self.slots, self.waiting, self.wait_s = slots, waiting, wait_s
        self.running = 0
        self._line: deque[asyncio.Future] = deque()

    @property
    def queued(self) -> int:
        return len(self._line)

    def admit(self) -> None:
        """``RenderBusy`` at once when every slot is taken and the line is full: a request that
        could not even wait is refused before anything is read or looked up for it."""
        if self.running >= self.slots and len(self._line) >= self.waiting:
            raise RenderBusy(f"{self.running} renders are running and {len(self._line)} waiting")

    @asynccontextmanager
    async def slot(self):
        if self.running < self.slots and not self._line:
            self.running += 1
        else:
            if len(self._line) >= self.waiting:
                raise RenderBusy(f"{self.running} renders are running and {len(self._line)} waiting")
            turn = asyncio.get_running_loop().create_future()
            self._line.append(turn)
            try:
                await asyncio.wait_for(turn, self.wait_s)  # the releasing render hands its slot over
            except TimeoutError:
                raise RenderBusy(f"no render slot came free within {self.wait_s:.0f} s") from None
            finally:
                if turn in self._line:
                    self._line.remove(turn)
        try:
            yield
        finally:
            self._release()

    def _release(self) -> None:
        while self._line:
            turn = self._line.popleft()
            if not turn.done():
                turn.set_result(None)  # the slot passes on: ``running`` stays
                return
        self.running -= 1


@dataclass
class LoadedAvatar:
    """An avatar directory in memory, and the lock of its renders (one at a time)."""

    avatar: Avatar
    frames: AvatarFrames | None
    coverage: Coverage | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)


class AvatarCache:
    """Up to ``capacity`` avatars kept loaded (LRU), and one body model per name (loaded once).
    Concurrent first requests for one avatar wait for a single load (``loads`` counts them)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.loads = 0
        self._avatars: OrderedDict[tuple[str, float], LoadedAvatar] = OrderedDict()
        self._loading: dict[tuple[str, float], threading.Lock] = {}
        self._bodies: dict[str, BodyModel] = {}
        self._lock = threading.Lock()
        self._body_lock = threading.Lock()

    def body(self, name: str) -> BodyModel:
        with self._body_lock:
            if name not in self._bodies:
                self._bodies[name] = load_body_model(name)
            return self._bodies[name]

    def get(self, avatar_id: str, path: Path) -> LoadedAvatar:
        try:
            key = (avatar_id, path.stat().st_mtime)
        except FileNotFoundError as err:  # deleted since the request was checked
            raise AvatarFileError(f"avatar {avatar_id} has no files on disk") from err
        with self._lock:
            if key in self._avatars:
                self._avatars.move_to_end(key)
                return self._avatars[key]
            loading = self._loading.setdefault(key, threading.Lock())
        with loading:  # one thread loads; the others wait here and then find it cached
            with self._lock:
                if key in self._avatars:
                    return self._avatars[key]
            saved = load_saved_avatar(path, body=self.body(read_avatar_meta(path).body_model))
            loaded = LoadedAvatar(saved.avatar.eval(), saved.frames, saved.meta.coverage)
            with self._lock:
                self.loads += 1
                self._avatars[key] = loaded
                self._loading.pop(key, None)
                while len(self._avatars) > self.capacity:
                    self._avatars.popitem(last=False)
        return loaded

    def forget(self, avatar_id: str) -> None:
        with self._lock:
            for key in [k for k in self._avatars if k[0] == avatar_id]:
                del self._avatars[key]


# -- render (pose, camera and size come from eva_engine.avatar.render_spec) ------------------------
def checked_size(spec: RenderSpec, folder: Path, max_side: int, max_pixels: int) -> tuple[int, int]:
    """The render's (width, height), from the request and the avatar's ``avatar.json`` (no model
    load), or ``RenderInputError`` when it is over ``max_side`` a side or ``max_pixels`` in all."""
    frames = read_avatar_meta(folder).frames if uses_training_frame(spec) else None
    width, height = resolve_size(spec, frames.image_size if frames is not None else None)
    if width > max_side or height > max_side or width * height > max_pixels:
        raise RenderInputError(
            f"render size {width}x{height} is over the limit ({max_side} pixels a side, "
            f"{max_pixels} pixels in all); pass a smaller width / height"
        )
    return width, height


def render_image(loaded: LoadedAvatar, params: BodyParams, camera: Camera, background) -> np.ndarray:
    """[H, W, 3] uint8 (one render at a time per loaded avatar)."""
    with loaded.lock:
        return _render_image(loaded.avatar, params, camera, background)


def encode_image(image: np.ndarray, fmt: str) -> bytes:
    """[H, W, 3] uint8 -> the bytes of a PNG (``service.png``) or a JPEG (quality 92) file."""
    if fmt == "png":
        return encode_png(image)
    from PIL import Image

    buf = io.BytesIO()
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
