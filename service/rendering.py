"""Loaded avatars and what the render and export endpoints do with them: check the size and the
pose against the limits and the body model, build the camera, render through ``Avatar.render``
(at most ``RenderGate.slots`` at once), encode PNG/JPEG, and write the posed body mesh as GLB."""

from __future__ import annotations

import asyncio
import io
import threading
from collections import OrderedDict, deque
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from eva_engine.avatar import Avatar, AvatarFileError, load_avatar
from eva_engine.body import BodyModel, BodyParams, BodyPose, load_body_model
from eva_engine.render.camera import Camera, intrinsics, orbit_camera
from eva_engine.render.sh import SH_C0
from jobs.storage import FRAMES_NAME
from service.schemas import DEFAULT_DISTANCE, DEFAULT_FOV_Y, DEFAULT_SIZE, CameraSpec, RenderRequest


class RenderInputError(ValueError):
    """A render request that names something the avatar does not have, or asks for more than
    the limits (answered 422)."""


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
class TrainingFrames:
    """The training frames' fitted params (batch F), cameras K [F, 3, 3], viewmat [F, 4, 4] and
    image size (height, width)."""

    params: BodyParams
    K: torch.Tensor
    viewmat: torch.Tensor
    size: tuple[int, int]

    def __len__(self) -> int:
        return self.params.batch_size


@dataclass
class LoadedAvatar:
    avatar: Avatar
    frames: TrainingFrames | None
    lock: threading.Lock


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
            from eva_engine.avatar import read_avatar_info

            body = self.body(read_avatar_info(path)["body_model"])
            loaded = LoadedAvatar(load_avatar(path, body=body).eval(), _read_frames(path), threading.Lock())
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


def _read_frames(path: Path) -> TrainingFrames | None:
    from safetensors.torch import load_file

    from eva_engine.avatar import read_avatar_info

    file = path / FRAMES_NAME
    if not file.is_file():
        return None
    t = load_file(str(file))
    params = BodyParams(**{k.removeprefix("params."): v for k, v in t.items() if k.startswith("params.")})
    h, w = read_avatar_info(path).get("frames", {}).get("image_size", (0, 0))
    return TrainingFrames(params, t["K"], t["viewmat"], (int(h), int(w)))


# -- render ----------------------------------------------------------------------------------------
def resolve_size(req: RenderRequest, frame_size: tuple[int, int] | None) -> tuple[int, int]:
    """(width, height): as asked, else the training frames' (for ``frame``; ``frame_size`` is
    their (height, width) from ``avatar.json``), else 512."""
    if req.frame is not None and frame_size is not None and frame_size[0] > 0 and frame_size[1] > 0:
        h, w = frame_size
        if req.width is not None and req.height is None:
            return req.width, max(16, round(req.width * h / w))
        if req.height is not None and req.width is None:
            return max(16, round(req.height * w / h)), req.height
        return req.width or w, req.height or h
    return req.width or DEFAULT_SIZE, req.height or DEFAULT_SIZE


def checked_size(req: RenderRequest, folder: Path, max_side: int, max_pixels: int) -> tuple[int, int]:
    """The render's (width, height), from the request and the avatar's ``avatar.json`` (no model
    load), or ``RenderInputError`` when it is over ``max_side`` a side or ``max_pixels`` in all."""
    from eva_engine.avatar import read_avatar_info

    size = read_avatar_info(folder).get("frames", {}).get("image_size") if req.frame is not None else None
    width, height = resolve_size(req, (int(size[0]), int(size[1])) if size else None)
    if width > max_side or height > max_side or width * height > max_pixels:
        raise RenderInputError(
            f"render size {width}x{height} is over the limit ({max_side} pixels a side, "
            f"{max_pixels} pixels in all); pass a smaller width / height"
        )
    return width, height


def pose_params(loaded: LoadedAvatar, pose: BodyPose) -> BodyParams:
    """``pose`` as the avatar's body model's params, after checking its values against the
    model's own ranges (e.g. Anny's expressions and phenotypes in [0, 1])."""
    body = loaded.avatar.body
    for kind, values, bounds in (("expression", pose.expression, body.expression_bounds),
                                 ("shape", pose.shape, body.shape_bounds)):  # fmt: skip
        if bounds is None:
            continue
        lo, hi = bounds
        outside = [name for name, v in values.items() if not lo <= v <= hi]
        if outside:
            raise RenderInputError(
                f"{kind} value(s) of {outside[:8]} outside the {body.name} model's range [{lo}, {hi}]"
            )
    return body.params_from_pose(pose)


def frame_params(loaded: LoadedAvatar, index: int) -> BodyParams:
    frames = loaded.frames
    if frames is None:
        raise RenderInputError("this avatar keeps no training frames")
    if index >= len(frames):
        raise RenderInputError(f"frame {index} is out of range: the avatar has {len(frames)} training frames")
    return frames.params[index]


def make_camera(req: RenderRequest, width: int, height: int, frames: TrainingFrames | None) -> Camera:
    spec = req.camera
    if spec is None and req.frame is not None and frames is not None:
        # The training frame's own camera, with K scaled to the requested size.
        h0, w0 = frames.size
        K = frames.K[req.frame].clone().float()
        K[0] *= width / w0
        K[1] *= height / h0
        return Camera(K, frames.viewmat[req.frame].float(), width, height)
    spec = spec or CameraSpec()
    if spec.K is not None and spec.viewmat is not None:
        return Camera(torch.tensor(spec.K), torch.tensor(spec.viewmat), width, height)
    view = orbit_camera(
        spec.yaw or 0.0,
        spec.pitch or 0.0,
        spec.distance or DEFAULT_DISTANCE,
        spec.target or (0.0, 0.0, 0.0),
    )
    return Camera(intrinsics(width, height, spec.fov_y or DEFAULT_FOV_Y), view, width, height)


def render_image(loaded: LoadedAvatar, params: BodyParams, camera: Camera, background) -> np.ndarray:
    """[H, W, 3] uint8."""
    with loaded.lock, torch.no_grad():
        image = loaded.avatar.render(params, camera, torch.tensor(background, dtype=torch.float32))
    return (image.cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


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
