"""Expression fidelity: whether the mouth and eye opening of a video survive to the avatar.

Two measures per frame, from MediaPipe's 478 face-mesh landmarks (pixel coordinates):

- **mouth opening**: the inner-lip gap, landmarks 13-14;
- **eye opening**: the mean of the lid gaps 159-145 and 386-374;

both divided by the distance between the outer eye corners, 33-263. That scale, unlike the
face height 10-152, lies inside the fitted face-mesh correspondence (whose silhouette points
are not valid, ``align.face_mesh``), so every stage below is measured with the same ruler.

Stages of one frame, each compared with the detector on the target frame (:func:`agreement`):

- ``detected``: the landmarks preprocessing stored (tracked over the video, smoothed);
- ``fitted``: the fitted body's correspondence points, posed with the frame's parameters and
  projected with its camera (what the fit kept of the expression);
- ``render``: the same detector on the avatar's render of the frame (what training kept).

The detector runs on single images (no tracking) for the target and the render alike.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

MOUTH = (13, 14)
EYES = ((159, 145), (386, 374))
SCALE = (33, 263)
LANDMARKS_USED = (*MOUTH, *EYES[0], *EYES[1], *SCALE)
MEASURES = ("mouth", "eyes")


def openings(landmarks: Tensor, found: Tensor | None = None) -> dict[str, Tensor]:
    """Mouth and eye opening of each frame.

    landmarks: [F, 478, >=2] pixel coordinates (x, y first); found: [F] bool, the frames whose face
    was detected (default: every frame). Returns {"mouth": [F], "eyes": [F]}, NaN where the face
    was not found or its scale is zero.
    """
    if landmarks.ndim != 3 or landmarks.shape[1] < max(LANDMARKS_USED) + 1 or landmarks.shape[2] < 2:
        raise ValueError(f"landmarks must be [F, 478, >=2], got {tuple(landmarks.shape)}")
    xy = landmarks[..., :2].to(torch.float64)

    def gap(a: int, b: int) -> Tensor:
        return (xy[:, a] - xy[:, b]).norm(dim=-1)

    scale = gap(*SCALE)
    ok = scale > 0
    if found is not None:
        ok = ok & found.to(torch.bool)
    nan = torch.full_like(scale, float("nan"))
    safe = torch.where(ok, scale, torch.ones_like(scale))
    mouth = torch.where(ok, gap(*MOUTH) / safe, nan)
    eyes = torch.where(ok, 0.5 * (gap(*EYES[0]) + gap(*EYES[1])) / safe, nan)
    return {"mouth": mouth, "eyes": eyes}


@dataclass(frozen=True)
class Agreement:
    """How one stage's measure follows the target's over the frames both have.

    r: Pearson correlation (NaN when either side does not vary); target_range / stage_range:
    (5th, 95th) percentiles; range_ratio: the stage's 5-95 spread over the target's; frames:
    how many frames entered. full_range_ratio: the stage's max - min over the target's, the range
    issue 39's table gave. They differ for a blink: a clip's test frames sample each blink once or
    twice, so its closed eyes are a few percent of them and the 5-95 spread leaves them out (it
    weighs half-closed eyes instead); the full range rests on the one most closed and the one
    most open frame.
    """

    r: float
    target_range: tuple[float, float]
    stage_range: tuple[float, float]
    range_ratio: float
    frames: int
    full_range_ratio: float

    def to_json(self) -> dict:
        return asdict(self)


def _spread(x: Tensor) -> tuple[float, float]:
    q = torch.quantile(x, torch.tensor([0.05, 0.95], dtype=x.dtype))
    return float(q[0]), float(q[1])


def agreement(target: Tensor, stage: Tensor) -> Agreement:
    """target, stage: [F] one measure per frame (NaN: not measured). Frames where either is NaN
    are left out; with fewer than 3 frames left everything is NaN."""
    if target.shape != stage.shape or target.ndim != 1:
        raise ValueError(
            f"target and stage must be [F] alike, got {tuple(target.shape)}, {tuple(stage.shape)}"
        )
    t, s = target.to(torch.float64), stage.to(torch.float64)
    ok = torch.isfinite(t) & torch.isfinite(s)
    n = int(ok.sum())
    nan = float("nan")
    if n < 3:
        return Agreement(nan, (nan, nan), (nan, nan), nan, n, nan)
    t, s = t[ok], s[ok]
    tc, sc = t - t.mean(), s - s.mean()
    denom = float(tc.norm() * sc.norm())
    r = float((tc * sc).sum()) / denom if denom > 0 else nan
    tr, sr = _spread(t), _spread(s)
    width = tr[1] - tr[0]
    ratio = (sr[1] - sr[0]) / width if width > 0 else nan
    full = float(t.max() - t.min())
    full_ratio = float(s.max() - s.min()) / full if full > 0 else nan
    return Agreement(r, tr, sr, ratio, n, full_ratio)


def fitted_landmarks(model, params, regressor, landmark_ids: Tensor, K: Tensor, viewmat: Tensor) -> Tensor:
    """The fitted body's face-mesh points in the image: [F, 478, 3] (x px, y px, 1 where the
    correspondence has the landmark, else 0 and x = y = 0).

    model: ``BodyModel``; params: ``BodyParams`` of F frames; regressor, landmark_ids: from
    ``FaceMeshCorrespondence.regressor(model)``; K: [F, 3, 3]; viewmat: [F, 4, 4].
    """
    from eva_engine.geometry import project_points, to_camera

    with torch.no_grad():
        world = model.posed_points(params, regressor)  # [F, L, 3]
        pix = project_points(to_camera(world, viewmat.to(world)), K.to(world))
    out = torch.zeros(pix.shape[0], 478, 3, dtype=pix.dtype)
    out[:, landmark_ids, :2] = pix.cpu()
    out[:, landmark_ids, 2] = 1.0
    return out


def surface_gaps(model, params, regressor, landmark_ids: Tensor, pairs) -> Tensor:
    """[F, Q] metres: the 3D distance between the posed correspondence points of each landmark
    pair ((a, b), ... MediaPipe indices the correspondence has), e.g. ``MOUTH`` and ``EYES``: the
    openings of the body surface itself, before any camera.

    model: ``BodyModel``; params: ``BodyParams`` of F frames; regressor, landmark_ids: from
    ``FaceMeshCorrespondence.regressor(model)``.
    """
    at = {int(k): i for i, k in enumerate(landmark_ids)}
    a = torch.tensor([at[p] for p, _ in pairs])
    b = torch.tensor([at[q] for _, q in pairs])
    with torch.no_grad():
        pts = model.posed_points(params, regressor)  # [F, L, 3]
    return (pts[:, a] - pts[:, b]).norm(dim=-1)
