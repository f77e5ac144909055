"""The on-disk dataset layout (``eva-dataset`` v1, see ``docs/dataset-format.md``): a writer that
builds a dataset atomically, and a loader that returns torch tensors.

    with DatasetWriter(root, DatasetMeta(source="video", fps=30.0, image_size=(h, w))) as w:
        for ...:
            w.add_frame(rgb, mask, K=K, viewmat=viewmat, time=t)
        w.finish({"train": [...], "test_pose": [...]}, params=..., params_names=...)
    ds = load_dataset(root)
    frame = ds[0]  # Frame(image [H, W, 3], mask [H, W], region masks, K, viewmat, time)

No pickle: JSON, PNG and safetensors only.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from eva_engine.body.params import BodyParams
from eva_engine.data.face_crops import FaceCrops, load_face_crops

FORMAT = "eva-dataset"
VERSION = 2
SPLITS = ("train", "test_pose", "test_view", "test_far_pose", "test_far_view")
"""Frame sets (``docs/dataset-format.md``); the last two only the novel-pose benchmark fills."""
REGION_MASKS = ("hand_left", "hand_right", "face")
"""Per-frame region masks (the subject's left and right hand, the face): version 2 and later."""
REGIONS = ("person", *REGION_MASKS)
PARAM_FIELDS = ("root_orient", "transl", "joints", "expression", "shape")


class DatasetError(ValueError):
    """A folder is not a readable dataset (missing or malformed files)."""


@dataclasses.dataclass(frozen=True)
class ParamNames:
    """Column names of a ``BodyParams`` table: the body model's ``pose_joint_names``,
    ``expression_names`` and ``shape_names``."""

    joints: list[str]
    expression: list[str]
    shape: list[str]

    @classmethod
    def of(cls, model) -> ParamNames:
        """The names of a :class:`~eva_engine.body.BodyModel`'s parameters."""
        return cls(list(model.pose_joint_names), list(model.expression_names), list(model.shape_names))

    def check(self, params: BodyParams) -> None:
        sizes = (params.joints.shape[1], params.expression.shape[1], params.shape.shape[1])
        if sizes != (len(self.joints), len(self.expression), len(self.shape)):
            raise ValueError(
                f"parameter names ({len(self.joints)} joints, {len(self.expression)} expressions, "
                f"{len(self.shape)} shape) do not match the parameters {sizes}"
            )


@dataclasses.dataclass
class DatasetMeta:
    """``meta.json`` (see the format doc). The writer fills ``num_frames``, ``timestamps``, the
    ``*_source`` fields of what it wrote and the ``has_*`` flags."""

    source: str
    fps: float
    image_size: tuple[int, int]
    """(height, width)."""
    num_frames: int = 0
    name: str = ""
    body_model: str | None = None
    timestamps: list[float] = dataclasses.field(default_factory=list)
    background: tuple[float, float, float] | None = None
    camera_source: str = "estimated"
    params_source: str | None = None
    keypoints_source: str | None = None
    has_region_masks: bool = False
    has_ground_truth: bool = False
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)
    format: str = FORMAT
    version: int = VERSION

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["image_size"] = list(self.image_size)
        d["background"] = list(self.background) if self.background is not None else None
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> DatasetMeta:
        known = {f.name for f in dataclasses.fields(cls)}
        d = {k: v for k, v in d.items() if k in known}
        d["image_size"] = tuple(int(x) for x in d["image_size"])
        if d.get("background") is not None:
            d["background"] = tuple(float(x) for x in d["background"])
        return cls(**d)


@dataclasses.dataclass
class Frame:
    """One frame. image: [H, W, 3] float32 in [0, 1]; mask: [H, W] person coverage in [0, 1];
    regions: ``REGION_MASKS`` name -> [H, W] coverage (empty when the dataset has no region
    masks; a region not in the frame is an all-zero mask); K: [3, 3]; viewmat: [4, 4]; time: s."""

    index: int
    image: torch.Tensor
    mask: torch.Tensor
    K: torch.Tensor
    viewmat: torch.Tensor
    time: float
    regions: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)


class DatasetLike(Protocol):
    """What training and evaluation read of a dataset: :class:`Dataset` (a folder), a
    :class:`~eva_engine.data.resampled.ResampledDataset` view of one, or frames held in memory.

    meta: ``body_model`` (the parameters' body model) and ``background`` (the render background,
    None: white) are read; splits: split name -> frame indices; params: the frames' body
    parameters (batch ``len(ds)``) or None; gt_params: ground truth or None; ``ds[i]``: a
    :class:`Frame`.
    """

    @property
    def meta(self) -> DatasetMeta: ...

    @property
    def splits(self) -> dict[str, list[int]]: ...

    @property
    def params(self) -> BodyParams | None: ...

    @property
    def gt_params(self) -> BodyParams | None: ...

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...


# -- image files ---------------------------------------------------------------------------------
def _to_uint8(a: np.ndarray | torch.Tensor, what: str) -> np.ndarray:
    """uint8 arrays pass through; floats are taken as [0, 1] and rounded."""
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    a = np.asarray(a)
    if a.dtype == np.uint8:
        return a
    if a.dtype.kind not in "fiub":
        raise ValueError(f"{what} has dtype {a.dtype}; expected uint8 or float in [0, 1]")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{what} has NaN or Inf values")
    return np.clip(np.round(a * 255.0), 0, 255).astype(np.uint8)


def _write_png(path: Path, a: np.ndarray) -> None:
    import cv2

    img = a[..., ::-1] if a.ndim == 3 else a  # cv2 wants BGR
    if not cv2.imwrite(str(path), np.ascontiguousarray(img)):
        raise OSError(f"could not write {path}")


def _read_png(path: Path, channels: int) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise DatasetError(f"missing file {path}")
    a = cv2.imread(str(path), cv2.IMREAD_COLOR if channels == 3 else cv2.IMREAD_GRAYSCALE)
    if a is None:
        raise DatasetError(f"cannot decode image {path}")
    return a[..., ::-1].copy() if channels == 3 else a


def _frame_name(i: int) -> str:
    return f"{i:06d}.png"


# -- safetensors tables ------------------------------------------------------------------------
def _save_params(path: Path, params: BodyParams, names: ParamNames, source: str) -> None:
    from safetensors.torch import save_file

    names.check(params)
    tensors = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in params.tensors().items()}
    meta = {
        "joint_names": json.dumps(names.joints),
        "expression_names": json.dumps(names.expression),
        "shape_names": json.dumps(names.shape),
        "source": source,
    }
    save_file(tensors, str(path), metadata=meta)


def _load_params(path: Path, n: int) -> tuple[BodyParams, ParamNames]:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in PARAM_FIELDS}
        names = ParamNames(
            json.loads(meta["joint_names"]),
            json.loads(meta["expression_names"]),
            json.loads(meta["shape_names"]),
        )
        params = BodyParams(**tensors)
        names.check(params)
    except Exception as err:
        raise DatasetError(f"cannot read body parameters from {path}: {err}") from err
    if params.batch_size != n:
        raise DatasetError(f"{path} holds body parameters for {params.batch_size} frames, expected {n}")
    return params, names


def _save_keypoints(
    path: Path,
    keypoints: torch.Tensor,
    names: Sequence[str],
    source: str,
    extras: Mapping[str, torch.Tensor] | None = None,
) -> None:
    from safetensors.torch import save_file

    meta = {"names": json.dumps(list(names)), "source": source}
    tensors = {"keypoints": keypoints}
    for name, t in (extras or {}).items():
        if name == "keypoints" or t.shape[0] != keypoints.shape[0]:
            raise ValueError(f"keypoint extra {name!r} must be a per-frame tensor [N, ...] named otherwise")
        tensors[name] = t
    save_file(
        {k: t.detach().to("cpu", torch.float32).contiguous() for k, t in tensors.items()},
        str(path),
        metadata=meta,
    )


def _load_keypoints(path: Path, n: int) -> tuple[torch.Tensor, list[str], dict[str, torch.Tensor]]:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            names = json.loads((f.metadata() or {})["names"])
            kp = f.get_tensor("keypoints")
            extras = {k: f.get_tensor(k) for k in f.keys() if k != "keypoints"}
    except Exception as err:
        raise DatasetError(f"cannot read keypoints from {path}: {err}") from err
    if kp.ndim != 3 or kp.shape[0] != n or kp.shape[2] != 3 or kp.shape[1] != len(names):
        raise DatasetError(f"{path} holds keypoints {tuple(kp.shape)}, expected [{n}, {len(names)}, 3]")
    if any(t.shape[0] != n for t in extras.values()):
        raise DatasetError(f"{path}: per-frame detector outputs do not have {n} rows")
    return kp, names, extras


# -- writer --------------------------------------------------------------------------------------
def _is_dataset(root: Path) -> bool:
    try:
        return json.loads((root / "meta.json").read_text()).get("format") == FORMAT
    except (OSError, ValueError, AttributeError):
        return False


class DatasetWriter:
    """Writes a dataset frame by frame into a hidden folder beside ``root``; :meth:`finish` moves
    it into place, so a dataset folder is always complete. Leaving the ``with`` block without a
    successful ``finish`` discards everything. An existing dataset at ``root`` is replaced only
    with ``overwrite=True``; a folder that is not a dataset is never replaced."""

    def __init__(self, root: str | Path, meta: DatasetMeta, overwrite: bool = False) -> None:
        self.root = Path(root)
        if self.root.exists():
            if not _is_dataset(self.root):
                raise FileExistsError(f"{self.root} exists and is not a dataset; not touching it")
            if not overwrite:
                raise FileExistsError(
                    f"{self.root} already holds a dataset (pass overwrite=True to replace it)"
                )
        self.meta = dataclasses.replace(meta, extra=dict(meta.extra))
        h, w = (int(x) for x in meta.image_size)
        if h <= 0 or w <= 0:
            raise ValueError(f"image_size must be positive, got {meta.image_size}")
        self.meta.image_size = (h, w)
        self.overwrite = overwrite
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.root.parent / f".{self.root.name}.partial-{uuid.uuid4().hex[:8]}"
        (self._tmp / "frames").mkdir(parents=True)
        (self._tmp / "masks" / "person").mkdir(parents=True)
        self._K: list[torch.Tensor] = []
        self._view: list[torch.Tensor] = []
        self._times: list[float] = []
        self._regions: bool | None = None
        self._done = False

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.discard()

    @property
    def num_frames(self) -> int:
        return len(self._K)

    def discard(self) -> None:
        """Drop the partial dataset (no-op after :meth:`finish`)."""
        if not self._done and self._tmp.exists():
            shutil.rmtree(self._tmp, ignore_errors=True)

    def add_frame(
        self,
        image: np.ndarray | torch.Tensor,
        mask: np.ndarray | torch.Tensor,
        *,
        K: torch.Tensor | np.ndarray,
        viewmat: torch.Tensor | np.ndarray,
        time: float | None = None,
        regions: Mapping[str, np.ndarray | torch.Tensor] | None = None,
    ) -> int:
        """Append frame ``num_frames``: image [H, W, 3] and masks [H, W] (uint8, or float in
        [0, 1]); K [3, 3]; viewmat [4, 4]; ``time`` in seconds (default ``index / fps``).
        ``regions``: a mask for every name of ``REGION_MASKS`` (all-zero where the region is not
        in the frame), for every frame or for none. Returns the frame index."""
        if self._done:
            raise RuntimeError("the dataset is already finished")
        h, w = self.meta.image_size
        img, m = _to_uint8(image, "image"), _to_uint8(mask, "mask")
        if img.shape != (h, w, 3) or m.shape != (h, w):
            raise ValueError(
                f"image {img.shape} / mask {m.shape} do not match the dataset's image size {(h, w)}"
            )
        if regions is not None and set(regions) != set(REGION_MASKS):
            raise ValueError(f"regions must hold exactly {list(REGION_MASKS)}, got {sorted(regions)}")
        has_regions = regions is not None
        if self._regions is not None and has_regions != self._regions:
            raise ValueError("region masks must be given for every frame or for none")
        K_, view = torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(viewmat, dtype=torch.float32)
        if K_.shape != (3, 3) or view.shape != (4, 4):
            raise ValueError(
                f"K must be [3, 3] and viewmat [4, 4], got {tuple(K_.shape)}, {tuple(view.shape)}"
            )
        if not (torch.isfinite(K_).all() and torch.isfinite(view).all()):
            raise ValueError("K and viewmat must be finite")
        i = self.num_frames
        name = _frame_name(i)
        _write_png(self._tmp / "frames" / name, img)
        _write_png(self._tmp / "masks" / "person" / name, m)
        for region in REGION_MASKS if has_regions else ():
            rm = _to_uint8(regions[region], f"{region} mask")
            if rm.shape != (h, w):
                raise ValueError(f"{region} mask {rm.shape} does not match the image size {(h, w)}")
            (self._tmp / "masks" / region).mkdir(exist_ok=True)
            _write_png(self._tmp / "masks" / region / name, rm)
        self._regions = has_regions
        self._K.append(K_)
        self._view.append(view)
        self._times.append(float(time) if time is not None else i / float(self.meta.fps))
        return i

    def finish(
        self,
        splits: Mapping[str, Sequence[int]],
        *,
        params: BodyParams | None = None,
        params_names: ParamNames | None = None,
        params_source: str | None = None,
        keypoints: torch.Tensor | None = None,
        keypoint_names: Sequence[str] | None = None,
        keypoints_source: str | None = None,
        keypoint_extras: Mapping[str, torch.Tensor] | None = None,
        gt_params: BodyParams | None = None,
        gt_keypoints: torch.Tensor | None = None,
        extra: Mapping[str, Any] | None = None,
    ) -> Path:
        """Write cameras, parameters, keypoints, splits and meta; move the dataset into place.

        params / gt_params: ``BodyParams`` with N rows (``params_names`` required);
        keypoints / gt_keypoints: [N, K, 3] (``keypoint_names`` required); keypoint_extras: other
        per-frame detector outputs stored beside ``keypoints`` (e.g. ``hand_depth [N, 42]``,
        ``pose_world [N, 33, 4]``). Returns the root."""
        if self._done:
            raise RuntimeError("the dataset is already finished")
        n = self.num_frames
        if n == 0:
            raise ValueError("a dataset needs at least one frame")
        unknown = [s for s in splits if s not in SPLITS]
        if unknown:
            raise ValueError(f"unknown split(s) {unknown}; valid splits: {list(SPLITS)}")
        out_splits = {s: [int(i) for i in splits.get(s, [])] for s in SPLITS}
        bad = [i for ids in out_splits.values() for i in ids if not 0 <= i < n]
        if bad:
            raise ValueError(f"split indices {bad} are outside the {n} frames")
        for what, p in (("params", params), ("gt_params", gt_params)):
            if p is not None:
                if params_names is None:
                    raise ValueError(f"{what} need params_names")
                if p.batch_size != n:
                    raise ValueError(f"{what} have {p.batch_size} rows, expected {n}")
        for what, k in (("keypoints", keypoints), ("gt_keypoints", gt_keypoints)):
            if k is not None:
                if keypoint_names is None:
                    raise ValueError(f"{what} need keypoint_names")
                if tuple(k.shape) != (n, len(keypoint_names), 3):
                    raise ValueError(
                        f"{what} have shape {tuple(k.shape)}, expected [{n}, {len(keypoint_names)}, 3]"
                    )

        from safetensors.torch import save_file

        tmp = self._tmp
        save_file(
            {"K": torch.stack(self._K), "viewmat": torch.stack(self._view)}, str(tmp / "cameras.safetensors")
        )
        meta = self.meta
        meta.params_source = (params_source or "unknown") if params is not None else None
        meta.keypoints_source = (keypoints_source or "unknown") if keypoints is not None else None
        if params is not None:
            _save_params(tmp / "params.safetensors", params, params_names, meta.params_source)
        if keypoints is not None:
            kp_path = tmp / "keypoints.safetensors"
            _save_keypoints(kp_path, keypoints, keypoint_names, meta.keypoints_source, keypoint_extras)
        if gt_params is not None or gt_keypoints is not None:
            (tmp / "ground_truth").mkdir()
        if gt_params is not None:
            _save_params(tmp / "ground_truth" / "params.safetensors", gt_params, params_names, "ground_truth")
        if gt_keypoints is not None:
            _save_keypoints(
                tmp / "ground_truth" / "keypoints.safetensors", gt_keypoints, keypoint_names, "ground_truth"
            )
        meta.num_frames = n
        meta.timestamps = list(self._times)
        meta.has_region_masks = bool(self._regions)
        meta.has_ground_truth = gt_params is not None or gt_keypoints is not None
        if extra:
            meta.extra.update(extra)
        (tmp / "splits.json").write_text(json.dumps(out_splits))
        (tmp / "meta.json").write_text(json.dumps(meta.to_json(), indent=1))

        # Swap into place: an old dataset is moved aside first and removed only after the rename.
        old = None
        if self.root.exists():
            if not (self.overwrite and _is_dataset(self.root)):
                raise FileExistsError(f"{self.root} appeared while writing; not replacing it")
            old = self.root.parent / f".{self.root.name}.old-{uuid.uuid4().hex[:8]}"
            self.root.rename(old)
        tmp.rename(self.root)
        self._done = True
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return self.root


# -- loader --------------------------------------------------------------------------------------
class Dataset:
    """A loaded dataset. Cameras, parameters and keypoints are in memory; images and masks are
    read from disk on access.

    K: [N, 3, 3]; viewmat: [N, 4, 4]; timestamps: [N] float64; params, gt_params: BodyParams or
    None; keypoints, gt_keypoints: [N, K, 3] or None; splits: {"train", "test_pose", "test_view"}.
    """

    def __init__(self, root: str | Path) -> None:
        from safetensors.torch import load_file

        self.root = Path(root)
        meta_path = self.root / "meta.json"
        if not meta_path.is_file():
            raise DatasetError(f"no meta.json in {self.root}: not a dataset")
        try:
            raw = json.loads(meta_path.read_text())
        except ValueError as err:
            raise DatasetError(f"{meta_path} is not valid JSON: {err}") from err
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise DatasetError(f"{meta_path}: format is {raw.get('format')!r}, expected {FORMAT!r}")
        if not isinstance(raw.get("version"), int) or raw["version"] > VERSION:
            raise DatasetError(
                f"{meta_path}: version {raw.get('version')!r} is newer than this reader ({VERSION})"
            )
        try:
            self.meta = DatasetMeta.from_json(raw)
        except (KeyError, TypeError, ValueError) as err:
            raise DatasetError(f"{meta_path} is malformed: {err}") from err
        # Version 1 stored both hands in one mask; per-hand regions start with version 2, so a
        # version-1 dataset is read without its region masks (regenerate it to get them).
        self.has_region_masks = self.meta.has_region_masks and self.meta.version >= 2
        n = self.meta.num_frames
        try:
            cams = load_file(str(self.root / "cameras.safetensors"))
            self.K, self.viewmat = cams["K"], cams["viewmat"]
        except Exception as err:
            raise DatasetError(f"cannot read cameras.safetensors in {self.root}: {err}") from err
        if self.K.shape != (n, 3, 3) or self.viewmat.shape != (n, 4, 4):
            raise DatasetError(
                f"cameras.safetensors holds K {tuple(self.K.shape)} and viewmat {tuple(self.viewmat.shape)}, "
                f"but meta.json says {n} frames"
            )
        if len(self.meta.timestamps) != n:
            raise DatasetError(f"meta.json has {len(self.meta.timestamps)} timestamps for {n} frames")
        self.timestamps = torch.tensor(self.meta.timestamps, dtype=torch.float64)
        try:
            raw_splits = json.loads((self.root / "splits.json").read_text())
            self.splits = {s: [int(i) for i in raw_splits.get(s, [])] for s in SPLITS}
        except (OSError, ValueError, TypeError, AttributeError) as err:
            raise DatasetError(f"cannot read splits.json in {self.root}: {err}") from err
        if any(not 0 <= i < n for ids in self.splits.values() for i in ids):
            raise DatasetError(f"splits.json in {self.root} lists frames outside 0..{n - 1}")

        self.params: BodyParams | None = None
        self.gt_params: BodyParams | None = None
        self.param_names: ParamNames | None = None
        for attr, rel in (("params", "params.safetensors"), ("gt_params", "ground_truth/params.safetensors")):
            if (self.root / rel).exists():
                p, names = _load_params(self.root / rel, n)
                setattr(self, attr, p)
                self.param_names = names
        self.face_crops: FaceCrops | None = load_face_crops(self.root, n)
        """The face close-ups at the video's resolution (``data.face_crops``), if it has them."""
        self.keypoints: torch.Tensor | None = None
        self.gt_keypoints: torch.Tensor | None = None
        self.keypoint_names: list[str] | None = None
        self.keypoint_extras: dict[str, torch.Tensor] = {}
        """Other per-frame detector outputs stored with ``keypoints`` (``hand_depth``, ``pose_world``)."""
        for attr, rel in (
            ("keypoints", "keypoints.safetensors"),
            ("gt_keypoints", "ground_truth/keypoints.safetensors"),
        ):
            if (self.root / rel).exists():
                k, names, extras = _load_keypoints(self.root / rel, n)
                setattr(self, attr, k)
                self.keypoint_names = names
                if attr == "keypoints":
                    self.keypoint_extras = extras

    # -- sizes -----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.meta.num_frames

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width)."""
        return self.meta.image_size

    def __repr__(self) -> str:
        sizes = {s: len(v) for s, v in self.splits.items()}
        return f"Dataset({str(self.root)!r}, source={self.meta.source!r}, frames={len(self)}, splits={sizes})"

    # -- per-frame access --------------------------------------------------------------------
    def _check_index(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} is outside 0..{len(self) - 1}")
        return i

    def image(self, i: int) -> torch.Tensor:
        """Frame ``i`` as [H, W, 3] float32 in [0, 1]."""
        i = self._check_index(i)
        a = _read_png(self.root / "frames" / _frame_name(i), 3)
        return self._checked(torch.from_numpy(a).float() / 255.0, i)

    def mask(self, i: int, region: str = "person") -> torch.Tensor:
        """Mask ``region`` (``REGIONS``: person, hand_left, hand_right, face) of frame ``i`` as
        [H, W] float32 in [0, 1]."""
        i = self._check_index(i)
        if region not in REGIONS:
            raise ValueError(f"unknown region {region!r}; choose one of {REGIONS}")
        if region != "person" and not self.has_region_masks:
            raise DatasetError(f"{self.root} has no {region} masks")
        a = _read_png(self.root / "masks" / region / _frame_name(i), 1)
        return self._checked(torch.from_numpy(a).float() / 255.0, i)

    def _checked(self, t: torch.Tensor, i: int) -> torch.Tensor:
        if tuple(t.shape[:2]) != self.image_size:
            raise DatasetError(f"frame {i} has size {tuple(t.shape[:2])}, meta.json says {self.image_size}")
        return t

    def __getitem__(self, i: int) -> Frame:
        i = self._check_index(i)
        regions = REGION_MASKS if self.has_region_masks else ()
        return Frame(
            index=i,
            image=self.image(i),
            mask=self.mask(i),
            K=self.K[i],
            viewmat=self.viewmat[i],
            time=float(self.timestamps[i]),
            regions={r: self.mask(i, r) for r in regions},
        )

    def images(self, indices: Sequence[int] | None = None) -> torch.Tensor:
        """[B, H, W, 3] for ``indices`` (default: all frames)."""
        ids = range(len(self)) if indices is None else indices
        return torch.stack([self.image(i) for i in ids])

    def masks(self, indices: Sequence[int] | None = None, region: str = "person") -> torch.Tensor:
        """[B, H, W] for ``indices`` (default: all frames)."""
        ids = range(len(self)) if indices is None else indices
        return torch.stack([self.mask(i, region) for i in ids])


def load_dataset(path: str | Path) -> Dataset:
    """Open a dataset folder (raises :class:`DatasetError` if it is not a valid one)."""
    return Dataset(path)
