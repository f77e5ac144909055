"""Driving sequences: the motion an avatar is made to perform, from a video of anyone (preprocessed
and aligned with the avatar's body model), from a dataset folder, or from a JSON file of poses.

A JSON sequence uses the API's pose schema, one ``BodyPose`` per frame::

    {"fps": 25, "poses": [{"joints": {"upperarm01.L": [0, 0, -1.1]}}, {"expression": {"jawOpen": 0.4}}]}

(a bare list of poses is read at 25 fps). Its poses are in the avatar's own terms, as in a
render request: they are not retargeted.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from eva_engine.align import PreprocessConfig, PreprocessError, preprocess_video
from eva_engine.avatar.render_spec import RenderInputError, RenderPose, check_pose_ranges
from eva_engine.body.model import BodyModel
from eva_engine.body.params import BodyParams, InvalidPoseError
from eva_engine.data import DatasetError, VideoError, load_dataset
from eva_engine.progress import Progress

MAX_POSES = 100_000
DEFAULT_POSES_FPS, MAX_POSES_FPS = 25.0, 240.0


class DrivingError(ValueError):
    """A driving input that cannot drive an avatar (unreadable, empty, no person, wrong model)."""


class PoseSequence(BaseModel):
    """A motion as JSON: ``poses`` (one pose per frame, within a render's bounds: ``RenderPose``)
    played at ``fps``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    fps: float = Field(DEFAULT_POSES_FPS, gt=0.0, le=MAX_POSES_FPS, description="Frames per second.")
    poses: list[RenderPose] = Field(
        ..., min_length=1, max_length=MAX_POSES, description="One pose per frame."
    )


@dataclass
class DrivingSequence:
    """T frames of motion.

    params: BodyParams [T] (the fitted person's shape for a video); times: [T] float64 seconds,
    increasing; fps: the source's frame rate; K [T, 3, 3], viewmat [T, 4, 4]: the driving
    camera per frame, image_size (height, width) and frames uint8 [T, H, W, 3] (the driving
    video's frames) -- all None for a JSON sequence; retarget: whether the motion belongs to
    another person (video, dataset) or is in the avatar's own terms (JSON); dropped: video frames
    where no person was found (not in the sequence).
    """

    params: BodyParams
    times: torch.Tensor
    fps: float
    K: torch.Tensor | None = None
    viewmat: torch.Tensor | None = None
    image_size: tuple[int, int] | None = None
    frames: np.ndarray | None = None
    retarget: bool = True
    dropped: int = 0

    def __len__(self) -> int:
        return self.params.batch_size

    @property
    def has_camera(self) -> bool:
        return self.K is not None and self.viewmat is not None

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])


def driving_from_poses(doc: dict | list, body: BodyModel) -> DrivingSequence:
    """A JSON pose sequence (``PoseSequence`` or a bare list of poses) -> its sequence. Raises
    ``DrivingError`` naming what is wrong (schema errors, unknown joint or expression names)."""
    if isinstance(doc, list):
        doc = {"poses": doc}
    try:
        seq = PoseSequence.model_validate(doc)
        for i, pose in enumerate(seq.poses):
            try:
                check_pose_ranges(body, pose)
            except RenderInputError as err:
                raise DrivingError(f"pose {i}: {err}") from err
        params = body.params_from_pose(seq.poses)
    except ValidationError as err:
        raise DrivingError(f"not a pose sequence: {_first_errors(err)}") from err
    except InvalidPoseError as err:
        raise DrivingError(str(err)) from err
    times = torch.arange(len(seq.poses), dtype=torch.float64) / seq.fps
    return DrivingSequence(params, times, seq.fps, retarget=False)


def _first_errors(err: ValidationError, count: int = 3) -> str:
    parts = [f"{'.'.join(str(x) for x in e['loc']) or '(top)'}: {e['msg']}" for e in err.errors()[:count]]
    more = len(err.errors()) - count
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


def driving_from_dataset(path: str | Path, body: BodyModel, dropped: int = 0) -> DrivingSequence:
    """A dataset folder with fitted params (``eva preprocess``) -> its sequence, all frames in
    time order, with the dataset's cameras and images."""
    try:
        ds = load_dataset(path)
    except DatasetError as err:
        raise DrivingError(str(err)) from err
    params = ds.params if ds.params is not None else ds.gt_params
    if params is None:
        raise DrivingError(f"{path} has no body parameters (preprocess it with the body model fit)")
    if ds.meta.body_model not in (None, body.name) or params.joints.shape[1] != len(body.pose_joint_names):
        raise DrivingError(
            f"{path} was fitted with body model {ds.meta.body_model!r}; the avatar's is {body.name!r}"
        )
    order = torch.argsort(ds.timestamps)
    ids = order.tolist()
    times = ds.timestamps[order].clone()
    if len(ids) > 1 and (times.diff() <= 0).any():  # duplicate times: space them by the frame rate
        times = times[0] + torch.arange(len(ids), dtype=torch.float64) / ds.meta.fps
    frames = (ds.images(ids).numpy() * 255.0 + 0.5).astype(np.uint8)
    return DrivingSequence(
        params=params[ids],
        times=times,
        fps=float(ds.meta.fps),
        K=ds.K[ids].float(),
        viewmat=ds.viewmat[ids].float(),
        image_size=tuple(ds.image_size),
        frames=frames,
        retarget=True,
        dropped=dropped,
    )


def driving_from_video(
    video: str | Path,
    body: BodyModel,
    config=None,
    progress: Progress | None = None,
    workdir: str | Path | None = None,
) -> DrivingSequence:
    """Preprocess and align ``video`` (any person, any proportions) with ``body`` -- decode,
    detect, fit (``eva_engine.align.preprocess_video`` with ``config``, a ``PreprocessConfig``)
    -- and read the result as a sequence. ``workdir``: where the dataset is written (kept);
    default a temporary folder, removed after. ``progress``: as in
    ``preprocess_video``. Raises ``DrivingError`` for an unreadable video or one without a person.
    """
    config = config or PreprocessConfig(face_crops=None)  # motion only: no face close-ups
    if not config.fit:
        raise DrivingError("a driving video must be aligned with the body model (fit=True)")
    tmp = None if workdir is not None else Path(tempfile.mkdtemp(prefix="eva-driving-"))
    out = Path(workdir) if workdir is not None else tmp / "dataset"
    try:
        try:
            report = preprocess_video(video, out, config, model=body, progress=progress, overwrite=True)
        except (VideoError, PreprocessError) as err:
            raise DrivingError(str(err)) from err
        return driving_from_dataset(out, body, dropped=report.dropped_frames)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def load_driving(
    path: str | Path,
    body: BodyModel,
    config=None,
    progress: Progress | None = None,
) -> DrivingSequence:
    """A driving sequence from ``path``: a ``.json`` pose sequence, a dataset folder, or a video
    (preprocessed with ``config``)."""
    path = Path(path)
    if not path.exists():
        raise DrivingError(f"no such file or folder: {path}")
    if path.is_dir():
        return driving_from_dataset(path, body)
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError) as err:
            raise DrivingError(f"{path} is not valid JSON: {err}") from err
        return driving_from_poses(doc, body)
    return driving_from_video(path, body, config, progress)
