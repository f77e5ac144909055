"""What MediaPipe's face mesh reads on a face beyond the correspondence's surface points: a
calibration of the detector, made by the project on the body model's own rendered faces.

The correspondence (``align.face_mesh``) ties each landmark to one point of the neutral face.
Under an expression MediaPipe's landmarks do not stay on those points: the lid and inner-lip
landmarks follow the lids' and lips' edges, which slide over the skin as they open and close,
and the detector's face prior pulls the rest. So the fit's optimum was not the true expression
even on the body model's own face (``docs/alignment.md``, "Eye and mouth openings").

:func:`build_calibration` renders the painted face with random facial actions from three views,
runs the face mesh on each render and regresses what it reads beyond the projected
correspondence points on the actions (ridge, with a constant): per landmark,
``offset = bias + expression @ gain``, in the face's own frame in units of the eye-corner
distance (x from landmark 33 to landmark 263, y that turned a quarter towards the image's down),
so one calibration serves any face size, position and roll. The fit adds the offset, in pixels,
to the projected points it compares with the detections (``FitConfig.detector_calibration``):
the model predicts what the detector would read of its face, and the expression moves until
that matches. Cached beside the correspondence and keyed by it.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from eva_engine.align.face_mesh import (
    SHIPPED_DIR,
    FaceMeshCorrespondence,
    cache_folder,
    cached_json,
    face_mesh_pixels,
    head_camera,
    painted_face_renderer,
)
from eva_engine.body.model import BodyModel
from eva_engine.geometry import project_points, to_camera
from eva_engine.render.mesh import MeshRenderer

logger = logging.getLogger(__name__)

VERSION = 2
FILE_NAME = "face_mesh_calibration.json"
EYE_CORNERS = (33, 263)
"""The outer eye corners (the subject's right, then left): the face frame's axis and unit."""
EYE_CONTOURS = frozenset(
    (7, 33, 133, 144, 145, 153, 154, 155, 157, 158, 159, 160, 161, 163, 173, 246)
    + (249, 263, 362, 373, 374, 380, 381, 382, 384, 385, 386, 387, 388, 390, 398, 466)
)
"""MediaPipe's eye outlines (``FACEMESH_LEFT_EYE`` and ``_RIGHT_EYE``), left uncalibrated: the lid
landmarks do not answer a blink linearly (the detector holds the lid open until the blink is
half done, then lets it go: ``docs/alignment.md``, "Where the gesturing clip's blink is lost"),
and calibrated they cost the eyes on synthetic and real video alike (``docs/alignment.md``)."""
VIEWS_DEG = ((0.0, 0.0), (-15.0, 5.0), (15.0, -5.0))
SAMPLES = 150
RIDGE = 1e-2


@dataclass(frozen=True)
class DetectorCalibration:
    """Per landmark (MediaPipe index ``landmarks [L]``): ``bias [L, 2]`` and ``gain [E, L, 2]``
    over the body model's ``E`` facial actions, in eye-corner units of the face frame."""

    landmarks: Tensor
    bias: Tensor
    gain: Tensor

    def aligned(self, landmarks: Tensor) -> DetectorCalibration:
        """The calibration of ``landmarks [K]`` in that order (zero for those it does not have)."""
        at = {int(k): i for i, k in enumerate(self.landmarks)}
        rows = torch.tensor([at.get(int(k), -1) for k in landmarks], dtype=torch.long)
        known = (rows >= 0).to(self.bias.dtype)[:, None]  # [K, 1]
        rows = rows.clamp_min(0)
        return DetectorCalibration(
            landmarks.clone(), self.bias[rows] * known, self.gain[:, rows] * known[None]
        )

    def offsets(self, expression: Tensor, corners: Tensor) -> Tensor:
        """[F, L, 2] pixels to add to the projected points of ``landmarks`` (``aligned`` to the
        points' order first). expression: [F, E]; corners: [F, 2, 3] the detected eye corners
        (x px, y px, confidence); a frame without both gets 0."""
        bias, gain = self.bias.to(expression), self.gain.to(expression)
        local = bias + torch.einsum("fe,eld->fld", expression, gain)  # [F, L, 2]
        axis = (corners[:, 1, :2] - corners[:, 0, :2]).to(expression)  # [F, 2], length = the unit
        found = ((corners[:, 0, 2] > 0) & (corners[:, 1, 2] > 0)).to(expression)[:, None]
        normal = torch.stack([-axis[:, 1], axis[:, 0]], dim=-1)
        return (local[..., :1] * axis[:, None] + local[..., 1:] * normal[:, None]) * found[:, None]

    def to_json(self) -> dict:
        return {
            "version": VERSION,
            "landmarks": self.landmarks.tolist(),
            "bias": self.bias.tolist(),
            "gain": self.gain.tolist(),
        }

    @classmethod
    def from_json(cls, d: dict) -> DetectorCalibration:
        return cls(
            torch.tensor(d["landmarks"], dtype=torch.int64),
            torch.tensor(d["bias"], dtype=torch.float32),
            torch.tensor(d["gain"], dtype=torch.float32),
        )


def random_expressions(names: list[str], samples: int, rng: np.random.Generator) -> np.ndarray:
    """[samples, E] sparse random expressions: one to four actions each, 0.2-1 (the first
    sample neutral), and in a third of them both eyes blinking together."""
    expr = np.zeros((samples, len(names)))
    blinks = [names.index(n) for n in ("eyeBlinkLeft", "eyeBlinkRight") if n in names]
    for i in range(1, samples):
        for j in rng.choice(len(names), size=int(rng.integers(1, 5)), replace=False):
            expr[i, j] = rng.uniform(0.2, 1.0)
        if blinks and rng.random() < 0.3:
            expr[i, blinks] = rng.uniform(0.3, 1.0)
    return expr


def build_calibration(
    model: BodyModel,
    corr: FaceMeshCorrespondence,
    samples: int = SAMPLES,
    views: tuple[tuple[float, float], ...] = VIEWS_DEG,
    seed: int = 0,
    renderer: MeshRenderer | None = None,
) -> DetectorCalibration:
    """The calibration of MediaPipe on ``model``'s painted face (module docstring). Needs the mesh
    renderer (EGL) and MediaPipe; about half a minute on two cores. ``renderer``: an open 512-pixel
    ``painted_face_renderer`` (else one is opened)."""
    x, y = calibration_readings(model, corr, samples, views, seed, renderer)
    names = list(model.expression_names)
    landmarks = corr.regressor(model)[1]
    if len(x) < 2 * len(names):
        raise RuntimeError(f"the face mesh found only {len(x)} of the calibration's renders")
    w = np.linalg.solve(x.T @ x + RIDGE * np.eye(x.shape[1]), x.T @ y)  # [1 + E, L * 2]
    fit = np.sqrt(((y - x @ w) ** 2).mean())
    logger.info(
        "face-mesh calibration: %d renders, residual %.4f -> %.4f eye-corner units",
        len(x),
        np.sqrt((y**2).mean()),
        fit,
    )
    w = torch.from_numpy(w).float().reshape(1 + len(names), len(landmarks), 2)
    kept = torch.tensor([int(k) not in EYE_CONTOURS for k in landmarks], dtype=torch.float32)[None, :, None]
    w = w * kept
    return DetectorCalibration(landmarks, w[0], w[1:])


def calibration_readings(
    model: BodyModel,
    corr: FaceMeshCorrespondence,
    samples: int = SAMPLES,
    views: tuple[tuple[float, float], ...] = VIEWS_DEG,
    seed: int = 0,
    renderer: MeshRenderer | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`build_calibration` regresses: ``x [S, 1 + E]`` (a constant, then each render's
    facial actions) and ``y [S, L * 2]`` (what the face mesh reads beyond the projected
    correspondence points, in the face's frame), over the renders where a face was found."""
    from mediapipe.python.solutions import face_mesh as mp_face_mesh

    reg, landmarks = corr.regressor(model)
    lm = landmarks.numpy()
    names = list(model.expression_names)
    expressions = random_expressions(names, samples, np.random.default_rng(seed))
    cameras = [head_camera(model, yaw, pitch, 512) for yaw, pitch in views]
    features, targets = [], []
    with (
        ExitStack() as stack,
        mp_face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True) as detector,
    ):
        if renderer is None:
            renderer = stack.enter_context(painted_face_renderer(model, 512))
        for expression in expressions:
            params = model.default_params(1)
            params.expression[0] = torch.from_numpy(expression).to(params.expression)
            with torch.no_grad():
                vertices = model(params).vertices[0]
                points = model.posed_points(params, reg)[0].double()
            for K, view in cameras:
                rgb = (renderer.render(vertices, view, K).rgb.numpy() * 255 + 0.5).astype(np.uint8)
                detected = face_mesh_pixels(detector, rgb)
                if detected is None:
                    continue
                uv = project_points(to_camera(points[None], view[None].double()), K[None].double())[0]
                features.append(expression)
                targets.append(in_face_frame(detected[lm] - uv.numpy(), detected))
    x = np.concatenate([np.ones((len(features), 1)), np.array(features).reshape(-1, len(names))], axis=1)
    return x, np.array(targets).reshape(len(features), 2 * len(lm))


def in_face_frame(offsets: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """[K, 2] pixel ``offsets`` in eye-corner units of the frame of ``detected [478, 2]``."""
    right, left = detected[EYE_CORNERS[0]], detected[EYE_CORNERS[1]]
    axis = left - right
    scale = float(np.linalg.norm(axis))
    ex = axis / scale
    ey = np.array([-ex[1], ex[0]])
    return np.stack([offsets @ ex, offsets @ ey], axis=-1) / scale


def cache_key(corr: FaceMeshCorrespondence) -> str:
    h = hashlib.sha256(json.dumps(corr.to_json()).encode())
    h.update(f"{VERSION}/{SAMPLES}/{VIEWS_DEG}/{RIDGE}/{sorted(EYE_CONTOURS)}".encode())
    return h.hexdigest()[:16]


def load_calibration(
    model: BodyModel,
    corr: FaceMeshCorrespondence,
    cache_dir: Path | None = None,
    renderer: Callable[[], MeshRenderer] | None = None,
) -> DetectorCalibration | None:
    """The cached calibration of ``model``'s face-mesh correspondence ``corr`` (built on first
    use), or None where it cannot be built (no renderer or MediaPipe, or no face found): the fit
    then compares the correspondence's points alone. ``renderer``: called for the renderer to
    build with, if it must (``face_mesh.shared_painted_face``)."""
    return cached_json(
        cache_folder(model, cache_dir) / FILE_NAME,
        cache_key(corr),
        "face-mesh calibration",
        lambda: build_calibration(model, corr, renderer=renderer() if renderer else None),
        DetectorCalibration.from_json,
        missing=(ImportError, RuntimeError),  # no renderer or MediaPipe, or no face found
        shipped=SHIPPED_DIR / f"{FILE_NAME}.gz",
    )
