"""Videos an avatar cannot be made from, told apart before the fit (issue 41's refusals).

After detection, :func:`refusal_reason` says in words why a video is refused, or None:

- **too short**: fewer frames with a person than ``min_frames``;
- **too small**: the person's median height (the person mask's rows) in the frames below
  ``min_person_px`` (before the next check: a small person's face and hands go unfound);
- **no body**: a body is found in too few frames. MediaPipe's pose model finds a "person" in a
  hand held up to the lens (measured on ``synth.hard``'s hand-alone clip: a pose with a face and
  shoulders in 8 of its 12 frames), so a frame counts only when the pose comes with a face or a hand
  that Holistic's own face and hand models confirm;
- **several people**: another person in most frames. Holistic tracks one person (its mask
  leaves the others out), so a few frames are looked at again with the tracked person painted
  over, by MediaPipe Pose on single images: a pose found there is someone else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class InputChecks:
    """When a video is refused. min_frames: frames with a person; min_body_share: share of the
    decoded frames with a confirmed body (pose and face or a hand); min_person_px: the person's
    median height, pixels of the dataset's frames; others_samples: frames looked at for another
    person (0: not looked for); max_others_share: share of those in which one may be."""

    min_frames: int = 1
    min_body_share: float = 0.3
    min_person_px: float = 80.0
    others_samples: int = 8
    max_others_share: float = 0.5

    def __post_init__(self) -> None:
        if self.min_frames < 1 or self.others_samples < 0 or self.min_person_px < 0:
            raise ValueError("min_frames must be >= 1, others_samples and min_person_px >= 0")
        if not (0.0 <= self.min_body_share <= 1.0 and 0.0 <= self.max_others_share <= 1.0):
            raise ValueError("min_body_share and max_others_share are shares in [0, 1]")


def body_found(found: dict[str, bool]) -> bool:
    """A frame shows a body: the pose, confirmed by the face or a hand model."""
    return bool(found.get("pose")) and any(found.get(k) for k in ("face", "left_hand", "right_hand"))


def person_height(mask: np.ndarray | None, keypoints: np.ndarray | None = None) -> float | None:
    """The person's height in one frame (pixels): the rows the mask [H, W] covers (> 0.5), else
    the span of the visible keypoints ([K, 3] with confidence); None when neither shows anyone."""
    if mask is not None:
        rows = np.flatnonzero((mask > 0.5).any(axis=1))
        if rows.size:
            return float(rows[-1] - rows[0] + 1)
    if keypoints is None:
        return None
    seen = keypoints[keypoints[:, 2] > 0.5]
    return float(np.ptp(seen[:, 1])) if len(seen) >= 2 else None


def _painted_over(frame: np.ndarray, mask: np.ndarray | None, keypoints: np.ndarray) -> np.ndarray:
    """``frame`` [H, W, 3] uint8 with the tracked person's box (mask and visible keypoints, 10%
    larger) filled with the median colour outside it."""
    h, w = frame.shape[:2]
    ys, xs = [], []
    if mask is not None and (mask > 0.5).any():
        yy, xx = np.nonzero(mask > 0.5)
        ys += [yy.min(), yy.max()]
        xs += [xx.min(), xx.max()]
    seen = keypoints[keypoints[:, 2] > 0.5]
    if len(seen):
        ys += [seen[:, 1].min(), seen[:, 1].max()]
        xs += [seen[:, 0].min(), seen[:, 0].max()]
    out = frame.copy()
    if not ys:
        return out
    y0, y1, x0, x1 = min(ys), max(ys), min(xs), max(xs)
    my, mx = 0.1 * (y1 - y0), 0.1 * (x1 - x0)
    y0, y1 = int(max(0, y0 - my)), int(min(h, y1 + my + 1))
    x0, x1 = int(max(0, x0 - mx)), int(min(w, x1 + mx + 1))
    outside = np.ones((h, w), bool)
    outside[y0:y1, x0:x1] = False
    fill = np.median(frame[outside], axis=0) if outside.any() else np.full(3, 127)
    out[y0:y1, x0:x1] = fill.astype(np.uint8)
    return out


def others_found(
    frames: list[np.ndarray], masks: list[np.ndarray | None], keypoints: np.ndarray
) -> list[bool]:
    """For each frame [H, W, 3] uint8 (with the tracked person's mask and keypoints [F, K, 3]):
    whether MediaPipe Pose finds a person once the tracked one is painted over."""
    from mediapipe.python.solutions import pose as mp_pose

    found = []
    with mp_pose.Pose(static_image_mode=True, model_complexity=1, min_detection_confidence=0.5) as detector:
        for frame, mask, kp in zip(frames, masks, keypoints, strict=True):
            result = detector.process(np.ascontiguousarray(_painted_over(frame, mask, kp)))
            landmarks = result.pose_landmarks
            visible = 0 if landmarks is None else sum(lm.visibility > 0.5 for lm in landmarks.landmark)
            found.append(visible >= 8)  # a few stray points are not a person
    return found


def refusal_reason(
    checks: InputChecks,
    found: list[dict[str, bool]],
    kept: list[int],
    heights: list[float | None],
    others: list[bool] | None = None,
) -> str | None:
    """Why the video is refused, or None. found: per decoded frame, what Holistic found; kept: the
    frames with a person; heights: per kept frame, the person's height (pixels); others: per
    sampled frame, whether someone else was found (None: not looked for)."""
    decoded = len(found)
    if len(kept) < checks.min_frames:
        return (
            f"a person was found in {len(kept)} of the video's {decoded} frames; an avatar needs at least "
            f"{checks.min_frames}: upload a longer video"
        )
    measured = [h for h in heights if h is not None]
    if measured and float(np.median(measured)) < checks.min_person_px:
        return (
            f"the person is only {float(np.median(measured)):.0f} px tall in the frames (median; at least "
            f"{checks.min_person_px:.0f} px needed): film closer, or upload a larger video"
        )
    bodies = sum(body_found(f) for f in found)
    if bodies < checks.min_body_share * decoded:
        return (
            f"a body was found in only {bodies} of {decoded} frames ({100 * bodies / max(decoded, 1):.0f}%; "
            f"at least {100 * checks.min_body_share:.0f}% needed): the video must show a person's body with "
            "the face or the hands, not a hand or an object alone"
        )
    if others:
        seen = sum(others)
        if seen > checks.max_others_share * len(others):
            return (
                f"another person is in {seen} of {len(others)} frames looked at: the video must show one "
                "person (crop it to one, or film one person at a time)"
            )
    return None
