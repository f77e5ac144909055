"""Face close-ups: the face at the video's own resolution, stored beside a dataset's frames.

A 1080p talking-head clip kept at 512 px leaves an open eye's lid gap 3-4 px tall
(``latentsync_demo3_gesturing``), too few pixels for a blink to show in the frame or to be
learnt from it. A close-up is a square around the frame's face (MediaPipe's face-mesh landmarks,
their larger extent grown by ``pad``), cut from the decoded frame at its full size and stored at
the video's own pixels across that square (median over the frames, a multiple of 16), at most
``size`` px a side. Its camera is the frame's camera restricted to that square
(:func:`crop_intrinsics`), so an avatar renders it from the same posed Gaussians as the frame.

Layout inside the dataset folder (written atomically, after the dataset itself):
``face_crops/boxes.safetensors`` (``boxes [N, 3]``: x0, y0, side in the frame's pixels, side 0
where the frame has no close-up; ``size``), ``face_crops/images/NNNNN.png`` and
``face_crops/masks/NNNNN.png`` for the frames that have one.
"""

from __future__ import annotations

import json
import shutil
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

FOLDER = "face_crops"


@dataclass(frozen=True)
class FaceCropConfig:
    """size: the largest close-up side (pixels); pad: the square's side over the face landmarks' larger
    extent; min_gain: store close-ups only when the decoded video has at least this many pixels
    across the face per pixel of the dataset's frame (median over frames): below it a close-up
    holds nothing the frame does not; min_side: frame pixels, smaller faces get none."""

    size: int = 256
    pad: float = 1.6
    min_gain: float = 1.5
    min_side: float = 24.0

    def __post_init__(self) -> None:
        if self.size < 16:
            raise ValueError(f"size must be >= 16, got {self.size}")
        if self.pad < 1.0:
            raise ValueError(f"pad must be >= 1, got {self.pad}")
        if self.min_gain <= 0.0:
            raise ValueError(f"min_gain must be > 0, got {self.min_gain}")


def crop_boxes(face_mesh: Tensor, image_size: tuple[int, int], config: FaceCropConfig) -> Tensor:
    """[N, 3] (x0, y0, side) squares around each frame's face in the frame's pixels (side 0 where
    no landmark was found or the face is under ``min_side``). face_mesh: [N, 478, >=3] x, y px and
    a confidence (0: not found); image_size: (h, w). A square may reach past the frame's edge:
    what lies outside is background in the close-up's mask."""
    xy, conf = face_mesh[..., :2].double(), face_mesh[..., 2] > 0
    boxes = torch.zeros(len(face_mesh), 3, dtype=torch.float64)
    for i in range(len(face_mesh)):
        if not bool(conf[i].any()):
            continue
        p = xy[i][conf[i]]
        lo, hi = p.amin(0), p.amax(0)
        extent = float((hi - lo).amax())
        if not np.isfinite(extent) or extent < config.min_side:
            continue
        side = config.pad * extent
        centre = 0.5 * (lo + hi)
        boxes[i] = torch.stack(
            [centre[0] - side / 2, centre[1] - side / 2, torch.tensor(side, dtype=torch.float64)]
        )
    return boxes.float()


def crop_intrinsics(K: Tensor, box: Tensor, size: int) -> Tensor:
    """[3, 3] intrinsics of the close-up ``box`` (x0, y0, side, frame pixels) rendered at ``size``
    px: the frame's ``K`` [3, 3] shifted to the square's corner and scaled (pixel centres stay at
    x + 0.5)."""
    s = size / box[2]
    out = K.clone()
    out[0, 0], out[1, 1] = K[0, 0] * s, K[1, 1] * s
    out[0, 1] = K[0, 1] * s
    out[0, 2] = (K[0, 2] - box[0]) * s
    out[1, 2] = (K[1, 2] - box[1]) * s
    return out


def _frame_to_crop(box: np.ndarray, size: int, scale: float) -> np.ndarray:
    """[2, 3] affine from close-up pixel indices to pixel indices of an image ``scale`` times
    the frame's size (pixel centres at index + 0.5 in both)."""
    k = box[2] / size
    return np.array(
        [
            [scale * k, 0.0, scale * (box[0] + 0.5 * k) - 0.5],
            [0.0, scale * k, scale * (box[1] + 0.5 * k) - 0.5],
        ]
    )


def cut_crop(image: np.ndarray, box: np.ndarray, size: int, scale: float, border: int = 0) -> np.ndarray:
    """The close-up ``box`` (frame pixels) of ``image`` [H, W, C] or [H, W] (``scale`` times the
    frame's size), ``size`` px a side, bilinear (blurred first where it shrinks, so it does not
    alias); outside the image: ``border``."""
    import cv2

    shrink = scale * box[2] / size
    if shrink > 1.25:
        image = cv2.GaussianBlur(image, (0, 0), 0.5 * shrink)
    return cv2.warpAffine(
        image,
        _frame_to_crop(box, size, scale),
        (size, size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=border,
    )


@dataclass
class FaceCrops:
    """A dataset's close-ups: ``boxes [N, 3]`` (x0, y0, side frame px; side 0: none), ``size``;
    images and masks read from ``root`` on access."""

    root: Path
    boxes: Tensor
    size: int

    def has(self, i: int) -> bool:
        return bool(self.boxes[i, 2] > 0)

    @property
    def frames(self) -> list[int]:
        """The frames that have a close-up."""
        return [int(i) for i in torch.nonzero(self.boxes[:, 2] > 0).flatten()]

    def intrinsics(self, i: int, K: Tensor) -> Tensor:
        """[3, 3] the close-up camera of frame ``i`` whose frame camera has ``K`` [3, 3]."""
        if not self.has(i):
            raise KeyError(f"frame {i} has no face close-up")
        return crop_intrinsics(K.float(), self.boxes[i], self.size)

    def image(self, i: int) -> Tensor:
        """[S, S, 3] float in [0, 1]."""
        return torch.from_numpy(self._read(self.root / "images" / _name(i), 3)).float() / 255.0

    def mask(self, i: int) -> Tensor:
        """[S, S] float in [0, 1]: the person mask."""
        return torch.from_numpy(self._read(self.root / "masks" / _name(i), 1)).float() / 255.0

    def _read(self, path: Path, channels: int) -> np.ndarray:
        from PIL import Image

        if not path.is_file():
            raise FileNotFoundError(f"{path} is missing: the dataset's face close-ups are incomplete")
        return np.array(Image.open(path).convert("RGB" if channels == 3 else "L"))


def _name(i: int) -> str:
    return f"{i:06d}.png"


def load_face_crops(dataset_root: str | Path, num_frames: int) -> FaceCrops | None:
    """The close-ups of the dataset at ``dataset_root`` (None when it has none)."""
    from safetensors.torch import load_file

    root = Path(dataset_root) / FOLDER
    path = root / "boxes.safetensors"
    if not path.is_file():
        return None
    data = load_file(str(path))
    boxes, size = data["boxes"].float(), int(data["size"])
    if boxes.shape != (num_frames, 3):
        raise ValueError(f"{path} holds boxes {tuple(boxes.shape)} for a dataset of {num_frames} frames")
    return FaceCrops(root, boxes, size)


def write_face_crops(
    dataset_root: str | Path,
    frames: Iterable[tuple[np.ndarray, float]],
    timestamps: Tensor,
    face_mesh: Tensor,
    masks: Tensor,
    config: FaceCropConfig,
) -> FaceCrops | None:
    """Cut and store a dataset's close-ups (replacing any it had); None when the video has too
    few pixels across the face to be worth it (``config.min_gain``).

    frames: (RGB uint8 [Hs, Ws, 3], seconds) of the decoded video, at any size with the frames'
    aspect; each is matched to the dataset frame with the same timestamp (``timestamps [N]``;
    decoded frames the dataset dropped are skipped). face_mesh: [N, 478, >=3] in the dataset's
    frame pixels; masks: [N, H, W] person masks in [0, 1]."""
    n, h, w = masks.shape
    boxes = crop_boxes(face_mesh, (h, w), config)
    wanted = boxes[:, 2] > 0
    at = {round(float(t), 6): j for j, t in enumerate(timestamps.tolist())}
    chosen: list[int] = []  # the close-ups' side, decided by the first decoded frame

    def cut() -> Iterator[tuple[int, np.ndarray, np.ndarray] | None]:
        for rgb, t in frames:
            j = at.get(round(float(t), 6))
            if j is None or not bool(wanted[j]):
                continue
            scale = rgb.shape[1] / w
            if not chosen:  # every decoded frame has the video's size
                chosen.append(close_up_size(scale, boxes[wanted, 2], config.size))
                if chosen[0] < 32 or chosen[0] / float(boxes[wanted, 2].median()) < config.min_gain:
                    yield None
                    return
            box = boxes[j].double().numpy()
            mask = (masks[j].clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
            yield j, cut_crop(rgb, box, chosen[0], scale), cut_crop(mask, box, chosen[0], 1.0)

    return store_face_crops(dataset_root, boxes, lambda: chosen[0], cut(), config)


def store_face_crops(
    dataset_root: str | Path,
    boxes: Tensor,
    size: int | Callable[[], int],
    crops: Iterable[tuple[int, np.ndarray, np.ndarray] | None],
    config: FaceCropConfig,
) -> FaceCrops | None:
    """Store close-ups in the dataset at ``dataset_root`` atomically, replacing any it had.

    boxes: [N, 3] (x0, y0, side) in frame pixels; size: the close-ups' side (or a function giving
    it once ``crops`` has started); crops: (frame, RGB uint8 [S, S, 3], mask uint8 [S, S]) per
    close-up, or None to give up (the dataset is then left with none). Frames ``crops`` skips
    keep no box. Returns the stored close-ups, or None."""
    root = Path(dataset_root)
    boxes = boxes.clone().float()
    tmp = root / f".{FOLDER}.partial-{uuid.uuid4().hex[:8]}"
    written = np.zeros(len(boxes), bool)
    try:
        (tmp / "images").mkdir(parents=True)
        (tmp / "masks").mkdir()
        for item in crops:
            if item is None:
                return _remove_crops(root, tmp)
            j, rgb, mask = item
            _write_png(tmp / "images" / _name(j), rgb)
            _write_png(tmp / "masks" / _name(j), mask)
            written[j] = True
        boxes[~torch.from_numpy(written)] = 0.0
        if not written.any():
            return _remove_crops(root, tmp)
        side = size() if callable(size) else size
        from safetensors.torch import save_file

        save_file({"boxes": boxes, "size": torch.tensor(side)}, str(tmp / "boxes.safetensors"))
        (tmp / "config.json").write_text(json.dumps({"size": side, "pad": config.pad}))
        old = root / FOLDER
        if old.exists():
            aside = root / f".{FOLDER}.old-{uuid.uuid4().hex[:8]}"
            old.rename(aside)
            shutil.rmtree(aside, ignore_errors=True)
        tmp.rename(old)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return load_face_crops(root, len(boxes))


def close_up_size(scale: float, sides: Tensor, largest: int) -> int:
    """The close-ups' side (pixels): the decoded video's pixels across the median square
    (``sides [M]`` in frame pixels, ``scale`` video pixels per frame pixel), down to a multiple
    of 16, at most ``largest``: a close-up never enlarges the video (0 for a face under 16 px)."""
    return int(min(largest, 16 * int(scale * float(sides.median()) // 16)))


def _remove_crops(root: Path, tmp: Path) -> None:
    """No close-ups: drop the partial folder and any the dataset had."""
    shutil.rmtree(tmp, ignore_errors=True)
    if (root / FOLDER).exists():
        shutil.rmtree(root / FOLDER)
    return None


def _write_png(path: Path, a: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(a).save(path, compress_level=1)
