"""Video -> dataset: decode, detect (MediaPipe Holistic), align the body model, write.

``preprocess_video`` is the in-the-wild front half of the pipeline (``eva preprocess``); its
output is an ``eva-dataset`` folder (docs/dataset-format.md) that ``eva train`` reads unchanged:
frames, person masks (holistic's segmentation), the guessed camera, detected keypoints with
their extras (hand depth, pose world landmarks), the fitted body parameters, and region masks
(each hand, the face) for evaluation: the fitted body's parts rendered with the frame's camera
and intersected with the person mask, for the hands and face the detector found in that frame
(``data.region_masks``).

Frames where no person is found are dropped and counted. A video an avatar cannot be made from
(no person, no body, too few frames, a person too small, several people: ``align.input_checks``)
is a :class:`PreprocessError` with the reason, raised before the fit.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from eva_engine.align.camera import GUESS_FOV_Y_DEG, guess_camera
from eva_engine.align.clip import ClipFit, fit_clip
from eva_engine.align.detect import DetectorConfig, FrameDetection, HolisticDetector
from eva_engine.align.input_checks import InputChecks, others_found, person_height, refusal_reason
from eva_engine.align.reprojection import reprojection_error
from eva_engine.align.stages import FitConfig
from eva_engine.align.targets import FitTargets
from eva_engine.body import KEYPOINT_NAMES, BodyModel, load_body_model
from eva_engine.body.params import BodyParams
from eva_engine.data import (
    DatasetMeta,
    DatasetWriter,
    ParamNames,
    VideoReadOptions,
    iter_frames,
    iter_timed_frames,
    load_dataset,
    read_video,
)
from eva_engine.data.face_crops import FaceCropConfig, FaceCrops, write_face_crops
from eva_engine.data.region_masks import region_masks
from eva_engine.progress import Progress, ProgressEvent


class PreprocessError(ValueError):
    """The video cannot become a dataset (no person found, unreadable file)."""


@dataclass(frozen=True)
class PreprocessConfig:
    """How a video becomes a dataset.

    every / max_frames / max_size: frame sampling and the longest image side (pixels);
    detect_max_size: the longest side of the frames the detector sees (None: as decoded). Hands
    and faces are small in whole-body video: MediaPipe's hand and face models crop them from the
    frame it is given, so a larger frame gives them more pixels and finds them more often
    (``bench/results/detection.md``); the detections are then scaled to ``max_size``.
    demuxer / max_video_side: read the video with this FFmpeg demuxer only and frames of at most
    this many pixels a side (``VideoReadOptions``: what an upload's check approved; None: FFmpeg
    guesses, no limit). fov_y_deg: the guessed camera's vertical field of view; test_every: every
    k-th kept frame goes to the ``test_pose`` split (0 = all frames train); fit: align the body
    model (else the dataset carries only detections); face_crops: the face close-ups at the
    video's resolution stored with the dataset (``data.face_crops``; None: none); checks: when
    the video is refused (``InputChecks``).
    """

    every: int = 1
    max_frames: int | None = 300
    max_size: int | None = 512
    detect_max_size: int | None = 1280
    demuxer: str | None = None
    max_video_side: int | None = None
    fov_y_deg: float = GUESS_FOV_Y_DEG
    test_every: int = 0
    fit: bool = True
    face_crops: FaceCropConfig | None = field(default_factory=FaceCropConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    fitting: FitConfig = field(default_factory=FitConfig)
    checks: InputChecks = field(default_factory=InputChecks)

    def __post_init__(self) -> None:
        if self.detect_max_size is not None and self.detect_max_size < 1:
            raise ValueError(f"detect_max_size must be >= 1, got {self.detect_max_size}")
        if self.test_every < 0 or self.test_every == 1:
            raise ValueError("test_every must be 0 (no test frames) or >= 2")
        if not 1.0 < self.fov_y_deg < 170.0:
            raise ValueError(f"fov_y_deg must be in (1, 170), got {self.fov_y_deg}")

    def read_options(self, max_frames: int | None, max_size: int | None):
        """How to read the video (``VideoReadOptions``): this config's sampling and source limits,
        ``max_frames`` kept frames at ``max_size`` pixels a side."""
        return VideoReadOptions(
            self.every, max_frames, max_size, demuxer=self.demuxer, max_side=self.max_video_side
        )


@dataclass
class Detections:
    """Stacked detector output for F frames (see ``align.detect`` for the fields)."""

    keypoints: np.ndarray  # [F, K, 3]
    hand_depth: np.ndarray  # [F, 42]
    pose_world: np.ndarray  # [F, 33, 4]
    masks: list[np.ndarray | None]
    found: list[dict[str, bool]]
    face_mesh: np.ndarray | None = None  # [F, 478, 3]
    face_depth: np.ndarray | None = None  # [F, 478]

    def targets(self, K: torch.Tensor, viewmat: torch.Tensor) -> FitTargets:
        return FitTargets(
            torch.from_numpy(self.keypoints),
            K,
            viewmat,
            torch.from_numpy(self.hand_depth),
            torch.from_numpy(self.pose_world),
            torch.from_numpy(self.face_mesh) if self.face_mesh is not None else None,
            self.person_masks(),
            torch.from_numpy(self.face_depth) if self.face_depth is not None else None,
        )

    def person_mask(self, row: int, shape: tuple[int, int]) -> np.ndarray:
        """[H, W] float32 frame ``row``'s person mask; all ones (the whole frame may be the person)
        where the segmenter gave none."""
        m = self.masks[row]
        return np.ones(shape, np.float32) if m is None else m.astype(np.float32, copy=False)

    def person_masks(self) -> torch.Tensor | None:
        """[F, H, W] the person masks, all ones where a frame has none (None without any mask)."""
        shapes = {m.shape for m in self.masks if m is not None}
        if len(shapes) != 1:
            return None
        (shape,) = shapes
        return torch.from_numpy(np.stack([self.person_mask(j, shape) for j in range(len(self.masks))]))

    def select(self, rows: list[int]) -> Detections:
        """The detections of frames ``rows``."""
        return Detections(
            self.keypoints[rows],
            self.hand_depth[rows],
            self.pose_world[rows],
            [self.masks[i] for i in rows],
            [self.found[i] for i in rows],
            self.face_mesh[rows] if self.face_mesh is not None else None,
            self.face_depth[rows] if self.face_depth is not None else None,
        )

    def regions_found(self) -> np.ndarray:
        """[F, 3] bool per frame: left hand, right hand, face found (``REGION_MASKS`` order)."""
        keys = ("left_hand", "right_hand", "face")
        return np.array([[f.get(k, False) for k in keys] for f in self.found], dtype=bool).reshape(-1, 3)

    def rates(self) -> dict[str, float]:
        """Fraction of frames in which each part was found."""
        n = max(len(self.found), 1)
        keys = ("pose", "left_hand", "right_hand", "face")
        return {k: sum(f.get(k, False) for f in self.found) / n for k in keys}


def detect_frames(
    frames: Iterable[np.ndarray],
    config: DetectorConfig | None = None,
    progress: Progress | None = None,
    total: int = 0,
    size: tuple[int, int] | None = None,
) -> Detections:
    """Run Holistic over RGB uint8 frames [H, W, 3] in order (tracking across them in video mode).
    size: (H, W) of the images the detections are for, when the frames show the same view at
    another size (``FrameDetection.resized``); None: the frames' own."""
    results: list[FrameDetection] = []
    with HolisticDetector(config) as detector:
        for i, frame in enumerate(frames):
            found = detector(frame)
            results.append(found.resized(frame.shape[:2], size) if size is not None else found)
            if progress is not None:
                message = f"detecting the person: frame {i + 1}/{total}"
                progress(ProgressEvent("detect", i + 1, total, message))
    if not results:
        return Detections(
            np.zeros((0, len(KEYPOINT_NAMES), 3), np.float32),
            np.zeros((0, 42), np.float32),
            np.zeros((0, 33, 4), np.float32),
            [],
            [],
        )
    return Detections(
        keypoints=np.stack([r.keypoints for r in results]),
        hand_depth=np.stack([r.hand_depth for r in results]),
        pose_world=np.stack([r.pose_world for r in results]),
        masks=[r.mask for r in results],
        found=[r.found for r in results],
        face_mesh=np.stack([r.face_mesh for r in results]),
        face_depth=np.stack([r.face_depth for r in results]),
    )


@dataclass
class PreprocessReport:
    """What preprocessing did: frame counts, detection rates, the fit's 2D errors (px)."""

    dataset: str
    decoded_frames: int
    kept_frames: int
    dropped_frames: int
    detection_rates: dict[str, float]
    reprojection_initial: dict[str, float]
    reprojection_fitted: dict[str, float]
    seconds: dict[str, float]

    def to_json(self) -> dict:
        clean = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}
        for key in ("reprojection_initial", "reprojection_fitted"):
            clean[key] = {k: (None if math.isnan(v) else v) for k, v in getattr(self, key).items()}
        return clean


def preprocess_video(
    video: str | Path,
    out_dir: str | Path,
    config: PreprocessConfig | None = None,
    model: BodyModel | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> PreprocessReport:
    """Turn one video of one person into a dataset at ``out_dir`` (written atomically).
    ``progress`` hears stages "decode", "detect", "align", "regions" and "write"."""
    config = config or PreprocessConfig()
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    clip = read_video(video, config.read_options(config.max_frames, config.max_size))
    seconds["decode"] = time.perf_counter() - started
    if progress is not None:
        progress(ProgressEvent("decode", len(clip), len(clip), f"decoded {len(clip)} frames"))

    det, keep, rates = _detect_one_person(video, clip, config, progress, seconds)
    h, w = clip.frames.shape[1:3]
    K, viewmat = guess_camera(w, h, config.fov_y_deg)
    body = _BodyFit(targets=det.targets(K, viewmat))
    if config.fit:
        model = model or load_body_model("anny")
        body = _fit_body(model, det, body.targets, clip.timestamps[keep], config, progress, seconds)
        body.regions = _region_masks(model, det, body, K, viewmat, (h, w), progress, seconds)
    started = time.perf_counter()
    root = _write_dataset(
        video, out_dir, clip, det, keep, body, K, viewmat, rates, model, config, progress, overwrite
    )
    seconds["write"] = time.perf_counter() - started
    face_mesh = body.targets.face_mesh
    if config.face_crops is not None and face_mesh is not None:
        started = time.perf_counter()
        # From what is in memory: the landmarks and masks the dataset was just written with.
        masks = body.targets.person_masks
        masks = masks if masks is not None else torch.ones(len(keep), h, w)
        times = torch.as_tensor(clip.timestamps[keep], dtype=torch.float64)
        _cut_face_crops(root, video, config, times, face_mesh, masks, progress)
        seconds["face_crops"] = time.perf_counter() - started
    n = len(keep)
    return PreprocessReport(str(root), len(clip), n, len(clip) - n, rates, body.initial, body.fitted, seconds)


@dataclass
class _BodyFit:
    """What fitting the body model gave (nothing but the targets when ``fit`` is off)."""

    targets: FitTargets
    params: BodyParams | None = None  # [F], the kept frames
    fit: ClipFit | None = None
    initial: dict[str, float] = field(
        default_factory=lambda: dict.fromkeys(("body", "hands", "face"), math.nan)
    )
    fitted: dict[str, float] = field(
        default_factory=lambda: dict.fromkeys(("body", "hands", "face"), math.nan)
    )
    hands: dict[str, int] = field(default_factory=lambda: {"rejected": 0, "filled": 0})
    regions: list | None = None


def _detect_one_person(video, clip, config: PreprocessConfig, progress, seconds: dict):
    """Detect the person in every frame and refuse a video no avatar can come from
    (``input_checks``): (the detections of the kept frames, their indices, the detection rates
    over all frames)."""
    started = time.perf_counter()
    h, w = clip.frames.shape[1:3]
    detect_long = max(clip.source_size)
    if config.detect_max_size is not None:
        detect_long = min(detect_long, config.detect_max_size)
    if detect_long == max(h, w):
        frames = iter(clip.frames)
    else:  # a second decoding pass, at the detector's size, frame for frame the same
        frames = iter_frames(video, config.read_options(len(clip), config.detect_max_size))
    det = detect_frames(frames, config.detector, progress, total=len(clip), size=(h, w))
    if len(det.found) != len(clip):
        raise PreprocessError(f"{video} decoded to {len(det.found)} frames on a second pass, not {len(clip)}")
    seconds["detect"] = time.perf_counter() - started
    keep = [i for i, f in enumerate(det.found) if f.get("pose", False)]
    if not keep:
        raise PreprocessError(
            f"no person was found in any of the {len(clip)} frames of {video}: the video must show one "
            "person, large enough to see"
        )
    started, checks = time.perf_counter(), config.checks
    others = None
    if checks.others_samples:
        rows = [
            keep[k]
            for k in np.unique(np.linspace(0, len(keep) - 1, checks.others_samples).round().astype(int))
        ]
        others = others_found(
            [clip.frames[i] for i in rows], [det.masks[i] for i in rows], det.keypoints[rows]
        )
    heights = [person_height(det.masks[i], det.keypoints[i]) for i in keep]
    reason = refusal_reason(checks, det.found, keep, heights, others)
    if reason is not None:
        raise PreprocessError(reason)
    seconds["checks"] = time.perf_counter() - started
    return det.select(keep), keep, det.rates()


def _fit_body(model, det, targets, timestamps, config: PreprocessConfig, progress, seconds: dict) -> _BodyFit:
    """The body model fitted to the clip (``fit_clip``) and its 2D errors before and after."""
    started = time.perf_counter()
    stages = len(config.fitting.stages)
    if progress is not None:
        progress(ProgressEvent("align", 0, stages, "fitting the body model"))
    fit = fit_clip(model, targets, torch.as_tensor(timestamps, dtype=torch.float64), config.fitting)
    found = det.regions_found()[:, :2] & ~fit.hands_rejected.numpy()
    filled = (fit.hand_confidence > 0) & ~torch.from_numpy(found)
    body = _BodyFit(
        targets=fit.targets,
        params=fit.params,
        fit=fit,
        initial=reprojection_error(model, fit.initial, fit.targets),
        fitted=reprojection_error(model, fit.params, fit.targets),
        hands={"rejected": int(fit.hands_rejected.sum()), "filled": int(filled.sum())},
    )
    seconds["align"] = time.perf_counter() - started
    if progress is not None:
        progress(ProgressEvent("align", stages, stages, "fitting the body model"))
    return body


def _region_masks(model, det, body: _BodyFit, K, viewmat, size, progress, seconds: dict) -> list:
    """Each frame's hand and face masks, scored where the detector found the region (a rejected
    hand was not found)."""
    started = time.perf_counter()
    person = [det.person_mask(j, size) for j in range(len(det.masks))]
    present = det.regions_found()
    present[:, :2] &= ~body.fit.hands_rejected.numpy()
    regions = region_masks(model, body.params, K, viewmat, size, person, present=present)
    seconds["regions"] = time.perf_counter() - started
    if progress is not None:
        progress(ProgressEvent("regions", len(regions), len(regions), "rendering hand and face regions"))
    return regions


def _write_dataset(
    video, out_dir, clip, det, keep, body: _BodyFit, K, viewmat, rates, model, config, progress, overwrite
):
    """The dataset's frames, masks, cameras, splits, parameters and keypoints: its folder."""
    h, w = clip.frames.shape[1:3]
    fitted = body.params is not None
    fps = clip.fps / config.every if clip.fps > 0 else 25.0
    meta = DatasetMeta(
        source="video",
        fps=fps,
        image_size=(h, w),
        name=Path(video).stem,
        body_model=model.name if fitted else None,
        camera_source="estimated",
    )
    n, targets, fit = len(keep), body.targets, body.fit
    test = list(range(config.test_every - 1, n, config.test_every)) if config.test_every else []
    train = [i for i in range(n) if i not in set(test)]
    with DatasetWriter(out_dir, meta, overwrite=overwrite) as writer:
        for j, i in enumerate(keep):
            writer.add_frame(
                clip.frames[i],
                det.person_mask(j, (h, w)),
                K=K,
                viewmat=viewmat,
                time=float(clip.timestamps[i]),
                regions=body.regions[j] if body.regions is not None else None,
            )
            if progress is not None:
                progress(ProgressEvent("write", j + 1, n, f"writing frame {j + 1}/{n}"))
        return writer.finish(
            {"train": train, "test_pose": test},
            params=body.params,
            params_names=ParamNames.of(model) if fitted else None,
            params_source="fitted",
            keypoints=targets.keypoints,
            keypoint_names=list(KEYPOINT_NAMES),
            keypoints_source="mediapipe",
            keypoint_extras={
                "hand_depth": targets.hand_depth,
                "pose_world": targets.pose_world,
                **({"face_mesh": targets.face_mesh} if targets.face_mesh is not None else {}),
                **({"face_depth": targets.face_depth} if targets.face_depth is not None else {}),
                **({"hand_confidence": fit.hand_confidence.float()} if fit is not None else {}),
            },
            extra={
                "video": str(Path(video).name),
                "detector": {"name": "mediapipe-holistic-0.10.21", **asdict(config.detector)},
                "frames": {"decoded": len(clip), "kept": n, "dropped": len(clip) - n, "every": config.every},
                "detection_rates": rates,
                "camera_guess": {"fov_y_deg": config.fov_y_deg},
                "reprojection_px": {
                    "initial": _nan_to_none(body.initial),
                    "fitted": _nan_to_none(body.fitted),
                },
                "hands": body.hands,
            },
        )


def add_face_crops(
    dataset_root: str | Path, video: str | Path, config: PreprocessConfig, progress: Progress | None = None
) -> FaceCrops | None:
    """Cut the face close-ups of the dataset at ``dataset_root``, made from ``video`` with
    ``config``'s sampling, from a decoding pass at the video's own size (``data.face_crops``;
    None when the video is too small for them to add anything). Also for a dataset written
    before close-ups existed."""
    ds = load_dataset(dataset_root)
    face_mesh = ds.keypoint_extras.get("face_mesh")
    if face_mesh is None:
        return None
    return _cut_face_crops(dataset_root, video, config, ds.timestamps, face_mesh, ds.masks(), progress)


def _cut_face_crops(dataset_root, video, config: PreprocessConfig, timestamps, face_mesh, masks, progress):
    """``write_face_crops`` from a decoding pass of ``video`` at its own size, with progress."""
    n = len(timestamps)
    if progress is not None:
        progress(ProgressEvent("face_crops", 0, n, "cutting face close-ups"))
    frames = iter_timed_frames(video, config.read_options(config.max_frames, None))
    crops = write_face_crops(
        dataset_root, frames, timestamps, face_mesh, masks, config.face_crops or FaceCropConfig()
    )
    if progress is not None:
        done = len(crops.frames) if crops is not None else 0
        progress(ProgressEvent("face_crops", n, n, f"{done} face close-ups"))
    return crops


def _nan_to_none(d: dict[str, float]) -> dict[str, float | None]:
    return {k: (None if math.isnan(v) else v) for k, v in d.items()}
