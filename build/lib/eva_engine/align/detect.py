"""2D keypoints and person masks from MediaPipe Holistic (legacy solution, models in the wheel).

``mediapipe==0.10.21`` ships the holistic, pose, hand and face-mesh TFLite models inside the
wheel; only ``model_complexity=1`` runs offline (0 and 2 download files at run time), so it is
fixed here. Output is the body models' keypoint layout (``eva_engine.body.KEYPOINT_NAMES``:
33 pose + 21 left hand + 21 right hand + 16 face points), the subject's left/right as in
holistic.

Per frame (image of H x W pixels):
    keypoints:  [K, 3] (x px, y px, confidence in [0, 1]); confidence 0 = not detected. Pose
                points carry MediaPipe's visibility; hand and face points 1 when their hand /
                the face was found.
    hand_depth: [42] relative depth of each hand landmark to its wrist, in pixels (MediaPipe's
                z times W: same scale as x; positive = farther from the camera).
    pose_world: [33, 4] metric 3D pose landmarks (x, y, z, visibility), hip-centred, camera-
                aligned axes (x right, y down, z away from the camera).
    face_mesh:  [478, 3] all face-mesh landmarks (x px, y px, confidence 1 when the face was
                found; the 10 iris points 0 without iris refinement), for dense face fitting.
    face_depth: [478] relative depth of each face-mesh landmark, in pixels (MediaPipe's z times
                W, centred on the landmarks' mean; positive = farther from the camera).
    mask:       [H, W] person probability in [0, 1] (holistic's segmentation).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from eva_engine.body import FACE_MESH_INDEX, KEYPOINT_GROUPS, KEYPOINT_NAMES

NUM_KEYPOINTS = len(KEYPOINT_NAMES)
FACE_MESH_POINTS = 478


class DetectorError(RuntimeError):
    """The detector could not run (mediapipe missing or broken)."""


@dataclass(frozen=True)
class DetectorConfig:
    """Holistic settings. ``video=True`` tracks across frames (faster, steadier); ``False`` treats
    every frame independently."""

    video: bool = True
    min_detection_confidence: float = 0.5
    min_tracking_confidence: float = 0.5
    refine_face_landmarks: bool = True
    segmentation: bool = True


@dataclass
class FrameDetection:
    """What the detector found in one frame (shapes in the module docstring)."""

    keypoints: np.ndarray
    hand_depth: np.ndarray
    pose_world: np.ndarray
    mask: np.ndarray | None
    found: dict[str, bool] = field(default_factory=dict)
    face_mesh: np.ndarray = field(default_factory=lambda: np.zeros((FACE_MESH_POINTS, 3), np.float32))
    face_depth: np.ndarray = field(default_factory=lambda: np.zeros(FACE_MESH_POINTS, np.float32))

    @property
    def has_person(self) -> bool:
        return self.found.get("pose", False)

    def resized(self, source: tuple[int, int], size: tuple[int, int]) -> FrameDetection:
        """This detection, made on an image of ``source`` = (H, W) pixels, in an image of ``size``
        = (H, W) showing the same view: pixel coordinates and hand depths scaled, the mask
        resampled, the metric pose world landmarks as they are."""
        if source == size:
            return self
        import cv2

        sy, sx = size[0] / source[0], size[1] / source[1]
        keypoints = self.keypoints.copy()
        keypoints[:, 0] *= sx
        keypoints[:, 1] *= sy
        face_mesh = self.face_mesh.copy()
        face_mesh[:, 0] *= sx
        face_mesh[:, 1] *= sy
        mask = None
        if self.mask is not None:
            mask = cv2.resize(self.mask, (size[1], size[0]), interpolation=cv2.INTER_AREA)
        # Hand and face depths are MediaPipe's z in units of the image width.
        hand_depth = self.hand_depth * np.float32(sx)
        face_depth = self.face_depth * np.float32(sx)
        return FrameDetection(
            keypoints, hand_depth, self.pose_world, mask, dict(self.found), face_mesh, face_depth
        )


class HolisticDetector:
    """MediaPipe Holistic as a context manager: ``with HolisticDetector() as det: det(frame)``.

    One instance per video (tracking state lives inside); frames are RGB uint8 [H, W, 3].
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        self.config = config or DetectorConfig()
        self._holistic = None

    def __enter__(self) -> HolisticDetector:
        try:
            from mediapipe.python.solutions import holistic
        except ImportError as err:  # pragma: no cover - install problem, not logic
            raise DetectorError(
                f"mediapipe is not importable ({err}); run `make install` (mediapipe==0.10.21 --no-deps)"
            ) from err
        cfg = self.config
        self._holistic = holistic.Holistic(
            static_image_mode=not cfg.video,
            model_complexity=1,  # the only one whose model ships in the wheel
            smooth_landmarks=cfg.video,
            enable_segmentation=cfg.segmentation,
            smooth_segmentation=cfg.video,
            refine_face_landmarks=cfg.refine_face_landmarks,
            min_detection_confidence=cfg.min_detection_confidence,
            min_tracking_confidence=cfg.min_tracking_confidence,
        )
        return self

    def __exit__(self, *exc) -> None:
        if self._holistic is not None:
            self._holistic.close()
            self._holistic = None

    def __call__(self, frame: np.ndarray) -> FrameDetection:
        if self._holistic is None:
            raise DetectorError("use HolisticDetector as a context manager: `with HolisticDetector() as d:`")
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ValueError(f"expected an RGB uint8 frame [H, W, 3], got {frame.dtype} {frame.shape}")
        result = self._holistic.process(np.ascontiguousarray(frame))
        return convert_holistic(result, frame.shape[1], frame.shape[0])


def _landmarks(proto, count: int) -> np.ndarray | None:
    """[count, 4] (x, y, z, visibility) from a NormalizedLandmarkList, or None."""
    if proto is None:
        return None
    out = np.array([(p.x, p.y, p.z, p.visibility) for p in proto.landmark], dtype=np.float32)
    return out if len(out) >= count else None


def convert_holistic(result, width: int, height: int) -> FrameDetection:
    """Holistic's result object -> :class:`FrameDetection` in the body models' layout."""
    keypoints = np.zeros((NUM_KEYPOINTS, 3), dtype=np.float32)
    hand_depth = np.zeros(42, dtype=np.float32)
    pose_world = np.zeros((33, 4), dtype=np.float32)
    scale = np.array([width, height], dtype=np.float32)
    found = {}

    pose = _landmarks(result.pose_landmarks, 33)
    found["pose"] = pose is not None
    if pose is not None:
        sl = KEYPOINT_GROUPS["pose"]
        keypoints[sl, :2] = pose[:33, :2] * scale
        keypoints[sl, 2] = np.clip(pose[:33, 3], 0.0, 1.0)
    world = _landmarks(getattr(result, "pose_world_landmarks", None), 33)
    if world is not None:
        pose_world[:] = world[:33]

    for side, proto in (("left", result.left_hand_landmarks), ("right", result.right_hand_landmarks)):
        hand = _landmarks(proto, 21)
        found[f"{side}_hand"] = hand is not None
        if hand is not None:
            sl = KEYPOINT_GROUPS[f"{side}_hand"]
            keypoints[sl, :2] = hand[:21, :2] * scale
            keypoints[sl, 2] = 1.0
            offset = 0 if side == "left" else 21
            hand_depth[offset : offset + 21] = (hand[:21, 2] - hand[0, 2]) * width

    face = _landmarks(result.face_landmarks, 468)
    found["face"] = face is not None
    face_mesh = np.zeros((FACE_MESH_POINTS, 3), dtype=np.float32)
    face_depth = np.zeros(FACE_MESH_POINTS, dtype=np.float32)
    if face is not None:
        n = min(len(face), FACE_MESH_POINTS)
        face_mesh[:n, :2] = face[:n, :2] * scale
        face_mesh[:n, 2] = 1.0
        face_depth[:n] = (face[:n, 2] - face[:n, 2].mean()) * width
        sl = KEYPOINT_GROUPS["face"]
        index = np.array(list(FACE_MESH_INDEX.values()))
        if len(face) <= index.max():  # no iris refinement: irises are not available
            index = np.where(index < len(face), index, 0)
            keypoints[sl, 2] = np.where(np.array(list(FACE_MESH_INDEX.values())) < len(face), 1.0, 0.0)
        else:
            keypoints[sl, 2] = 1.0
        keypoints[sl, :2] = face[index, :2] * scale

    mask = None
    if getattr(result, "segmentation_mask", None) is not None:
        mask = np.clip(np.asarray(result.segmentation_mask, dtype=np.float32), 0.0, 1.0)
    # Points outside the image are guesses (holistic extrapolates): keep them, but at most at
    # half confidence, so the fit leans on what was actually seen.
    outside = (
        (keypoints[:, 0] < 0)
        | (keypoints[:, 0] >= width)
        | (keypoints[:, 1] < 0)
        | (keypoints[:, 1] >= height)
    )
    keypoints[outside, 2] *= 0.5
    return FrameDetection(keypoints, hand_depth, pose_world, mask, found, face_mesh, face_depth)
