"""Reader for the XHumans dataset (licensed; for users who own it): maps one subject folder of
the public layout into the dataset layout (``docs/dataset-format.md``).

Public layout of a subject (e.g. ``00016/``)::

    gender.txt
    train/Take1/render/image/color_000001.png ...
    train/Take1/render/depth/depth_000001.tiff ...     (optional, used for person masks)
    train/Take1/render/cameras.npz                     intrinsic [3, 3], extrinsic [n, 3, 4]
    train/Take1/SMPLX/mesh-f00001_smplx.pkl ...        per-frame SMPL-X parameters
    test/Take4/...                                     the same

Training takes become ``train``; test takes become ``test_pose`` (whole novel-pose takes, as in
the paper). Parameters are SMPL-X (``body_model = "smplx"``), given to the pipeline as ground
truth. Person masks come from the depth maps, or from the background colour (the top-left
pixel) when a take has none. With the user's SMPL-X model (``model=load_body_model("smplx")``)
the reader also writes the region masks (each hand, the face) for the hand and face metrics:
the posed SMPL-X parts rendered with the frame's camera, intersected with the person mask
(``data.region_masks``). Pickles are read with a numpy-only unpickler: anything else is refused.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import torch

from eva_engine.body.params import BodyParams
from eva_engine.data.dataset import DatasetError, DatasetMeta, DatasetWriter, ParamNames

SMPLX_JOINT_NAMES = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "jaw",
    "left_eye_smplhf",
    "right_eye_smplhf",
    "left_index1",
    "left_index2",
    "left_index3",
    "left_middle1",
    "left_middle2",
    "left_middle3",
    "left_pinky1",
    "left_pinky2",
    "left_pinky3",
    "left_ring1",
    "left_ring2",
    "left_ring3",
    "left_thumb1",
    "left_thumb2",
    "left_thumb3",
    "right_index1",
    "right_index2",
    "right_index3",
    "right_middle1",
    "right_middle2",
    "right_middle3",
    "right_pinky1",
    "right_pinky2",
    "right_pinky3",
    "right_ring1",
    "right_ring2",
    "right_ring3",
    "right_thumb1",
    "right_thumb2",
    "right_thumb3",
)
"""SMPL-X's 55 kinematic joints (the ``smplx`` package's order); the root is ``pelvis``."""

_FRAME = re.compile(r"color_(\d+)\.png$")


@dataclasses.dataclass(frozen=True)
class XHumansOptions:
    """How to sample a subject."""

    train_every: int = 1
    test_every: int = 1
    test_per_take: int | None = None
    """At most this many frames per test take (after ``test_every``)."""
    max_size: int | None = None
    """Downscale so the longest image side is at most this (intrinsics follow)."""
    fps: float = 30.0
    mask_threshold: int = 8
    """Background-colour masks: a pixel differing by more than this (0-255) is the person."""

    def __post_init__(self) -> None:
        if self.train_every < 1 or self.test_every < 1:
            raise ValueError("train_every and test_every must be >= 1")
        if self.test_per_take is not None and self.test_per_take < 1:
            raise ValueError("test_per_take must be >= 1")


def _takes(root: Path, split: str) -> list[Path]:
    folder = root / split
    if not folder.is_dir():
        return []
    return sorted(t for t in folder.iterdir() if (t / "render" / "image").is_dir() and (t / "SMPLX").is_dir())


def _load_smplx(path: Path) -> dict[str, np.ndarray]:
    from eva_engine.numpy_pickle import UnsafePickleError, load_numpy_pickle

    try:
        d = load_numpy_pickle(path)
    except UnsafePickleError as err:
        raise DatasetError(f"refusing to load {path}: {err}") from err
    except Exception as err:
        raise DatasetError(f"cannot read SMPL-X parameters {path}: {err}") from err
    keys = (
        "betas",
        "global_orient",
        "body_pose",
        "left_hand_pose",
        "right_hand_pose",
        "jaw_pose",
        "leye_pose",
        "reye_pose",
        "expression",
        "transl",
    )
    if not isinstance(d, dict) or any(k not in d for k in keys):
        raise DatasetError(f"{path} lacks SMPL-X keys (need {list(keys)})")
    return {k: np.asarray(d[k], dtype=np.float32).reshape(-1) for k in keys}


def _params(frames: list[dict[str, np.ndarray]]) -> BodyParams:
    def stack(key: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([f[key] for f in frames]))

    n = len(frames)
    joints = torch.cat(
        [
            stack("body_pose").view(n, 21, 3),
            stack("jaw_pose").view(n, 1, 3),
            stack("leye_pose").view(n, 1, 3),
            stack("reye_pose").view(n, 1, 3),
            stack("left_hand_pose").view(n, 15, 3),
            stack("right_hand_pose").view(n, 15, 3),
        ],
        dim=1,
    )
    return BodyParams(
        root_orient=stack("global_orient"),
        transl=stack("transl"),
        joints=joints,
        expression=stack("expression"),
        shape=stack("betas"),
    )


def _read(path: Path, flags: int) -> np.ndarray:
    import cv2

    a = cv2.imread(str(path), flags)
    if a is None:
        raise DatasetError(f"cannot read image {path}")
    return a


def read_xhumans(
    subject: str | Path,
    out: str | Path,
    options: XHumansOptions | None = None,
    overwrite: bool = False,
    model=None,
) -> Path:
    """Convert one XHumans subject folder into a dataset at ``out``; returns ``out``. ``model``:
    a SMPL-X ``BodyModel`` (10 betas, 10 expressions) to render region masks with, or None."""
    import cv2

    from eva_engine.data.region_masks import RegionMaskRenderer

    opts = options or XHumansOptions()
    if model is not None and model.name != "smplx":
        raise ValueError(f"XHumans parameters are SMPL-X; region masks need that model, got {model.name!r}")
    root = Path(subject)
    takes = [("train", t) for t in _takes(root, "train")] + [("test", t) for t in _takes(root, "test")]
    if not takes:
        raise DatasetError(
            f"{root} is not in the XHumans layout: expected train/<Take>/render/image and SMPLX folders"
        )
    gender_file = root / "gender.txt"
    gender = gender_file.read_text().strip() if gender_file.is_file() else None
    writer = None
    regions = None
    frames_params: list[dict[str, np.ndarray]] = []
    source_frames: list[str] = []
    split_ids: dict[str, list[int]] = {"train": [], "test_pose": []}
    try:
        for split, take in takes:
            images = sorted((take / "render" / "image").glob("color_*.png"))
            images = [p for p in images if _FRAME.search(p.name)]
            every = opts.train_every if split == "train" else opts.test_every
            images = images[::every]
            if split == "test" and opts.test_per_take is not None:
                images = images[: opts.test_per_take]
            cams_path = take / "render" / "cameras.npz"
            try:
                with np.load(cams_path, allow_pickle=False) as cams:
                    intrinsic = np.asarray(cams["intrinsic"], np.float64)
                    extrinsic = np.asarray(cams["extrinsic"], np.float64)
            except Exception as err:
                raise DatasetError(f"cannot read cameras {cams_path}: {err}") from err
            for img_path in images:
                k = int(_FRAME.search(img_path.name).group(1))
                smplx_path = take / "SMPLX" / f"mesh-f{k:05d}_smplx.pkl"
                if not smplx_path.is_file():
                    raise DatasetError(f"missing SMPL-X parameters {smplx_path} for {img_path}")
                params = _load_smplx(smplx_path)
                if not 1 <= k <= len(extrinsic):
                    raise DatasetError(f"{cams_path} has no extrinsic for frame {k}")
                bgr = _read(img_path, cv2.IMREAD_COLOR)
                rgb = bgr[..., ::-1]
                depth_path = take / "render" / "depth" / f"depth_{k:06d}.tiff"
                if depth_path.is_file():
                    depth = _read(depth_path, cv2.IMREAD_UNCHANGED)
                    far = np.iinfo(depth.dtype).max if depth.dtype.kind in "ui" else np.inf  # "no surface"
                    mask = ((depth > 0) & (depth < far)).astype(np.float32)
                else:
                    diff = np.abs(rgb.astype(np.int16) - rgb[0, 0].astype(np.int16)).max(axis=-1)
                    mask = (diff > opts.mask_threshold).astype(np.float32)
                K = intrinsic.copy()
                h, w = rgb.shape[:2]
                if opts.max_size is not None and max(h, w) > opts.max_size:
                    s = opts.max_size / max(h, w)
                    size = (max(1, round(w * s)), max(1, round(h * s)))
                    K[:2] *= np.array([size[0] / w, size[1] / h])[:, None]
                    rgb = cv2.resize(np.ascontiguousarray(rgb), size, interpolation=cv2.INTER_AREA)
                    mask = cv2.resize(mask, size, interpolation=cv2.INTER_AREA)
                    h, w = rgb.shape[:2]
                view = np.eye(4)
                view[:3] = extrinsic[k - 1][:3]
                if writer is None:
                    meta = DatasetMeta(
                        source="xhumans",
                        fps=opts.fps,
                        image_size=(h, w),
                        name=f"xhumans-{root.name}",
                        body_model="smplx",
                        camera_source="ground_truth",
                    )
                    writer = DatasetWriter(out, meta, overwrite=overwrite)
                    regions = RegionMaskRenderer(model, (h, w)) if model is not None else None
                K_t, view_t = torch.from_numpy(K).float(), torch.from_numpy(view).float()
                masks = None
                if regions is not None:
                    with torch.no_grad():
                        vertices = model(_params([params]).to(model.dtype)).vertices[0]
                    masks = regions(vertices, view_t, K_t, mask)
                i = writer.add_frame(rgb, mask, K=K_t, viewmat=view_t, time=(k - 1) / opts.fps, regions=masks)
                split_ids["train" if split == "train" else "test_pose"].append(i)
                frames_params.append(params)
                source_frames.append(f"{split}/{take.name}/{img_path.name}")
        if writer is None:
            raise DatasetError(f"{root} is in the XHumans layout but holds no frames")
        params = _params(frames_params)
        names = ParamNames(
            list(SMPLX_JOINT_NAMES[1:]),
            [f"expr_{i}" for i in range(params.expression.shape[1])],
            [f"beta_{i}" for i in range(params.shape.shape[1])],
        )
        return writer.finish(
            split_ids,
            params=params,
            params_names=names,
            params_source="ground_truth",
            gt_params=params,
            extra={"subject": root.name, "gender": gender, "source_frames": source_frames},
        )
    finally:
        if writer is not None:
            writer.discard()
        if regions is not None:
            regions.close()
