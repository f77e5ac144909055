"""What the fit fits: a clip's detections and cameras (``FitTargets``), and which of
MediaPipe's 33 pose landmarks play which role."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.body import KEYPOINT_GROUPS

# Pose landmarks that are body joints (shoulders .. foot index); the others are face points
# and hand points that the face and hand groups measure better.
POSE_BODY = (11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32)
POSE_FACE = tuple(range(11))
POSE_HAND = (17, 18, 19, 20, 21, 22)
LEFT_HIP, RIGHT_HIP = 23, 24


@dataclass
class FitTargets:
    """What the fit is matched to, for F frames.

    keypoints:  [F, K, 3] detections (x px, y px, confidence); non-finite entries are dropped.
    K:          [F, 3, 3] or [3, 3] intrinsics; viewmat: [F, 4, 4] or [4, 4] world->camera.
    hand_depth: [F, 42] MediaPipe hand-landmark depth relative to the wrist, in pixels, or None.
    pose_world: [F, 33, 4] MediaPipe metric pose world landmarks + visibility, or None.
    face_mesh:  [F, 478, 3] MediaPipe face-mesh landmarks (x px, y px, confidence), or None.
    person_masks: [F, H, W] person masks in [0, 1] (the silhouette term, ``align.silhouette``),
                or None; a frame without a mask is all ones (it then contributes nothing).
    face_depth: [F, L] MediaPipe face-mesh landmark depth relative to their mean, in pixels, or
                None (weighted by ``face_mesh``'s confidence).
    """

    keypoints: Tensor
    K: Tensor
    viewmat: Tensor
    hand_depth: Tensor | None = None
    pose_world: Tensor | None = None
    face_mesh: Tensor | None = None
    person_masks: Tensor | None = None
    face_depth: Tensor | None = None

    def __post_init__(self) -> None:
        kp = torch.as_tensor(self.keypoints, dtype=torch.float32)
        if kp.ndim != 3 or kp.shape[-1] != 3:
            raise ValueError(f"keypoints must be [F, K, 3], got {tuple(kp.shape)}")
        f = kp.shape[0]
        ok = torch.isfinite(kp).all(-1) & (kp[..., 2] > 0)
        conf = torch.where(ok, kp[..., 2].clamp(0.0, 1.0), torch.zeros_like(kp[..., 2]))
        xy = torch.where(ok[..., None], kp[..., :2], torch.zeros_like(kp[..., :2]))
        self.keypoints = torch.cat([xy, conf[..., None]], dim=-1)
        self.K = torch.as_tensor(self.K, dtype=torch.float32)
        self.viewmat = torch.as_tensor(self.viewmat, dtype=torch.float32)
        if self.K.shape not in ((3, 3), (f, 3, 3)) or self.viewmat.shape not in ((4, 4), (f, 4, 4)):
            raise ValueError(
                f"K must be [3, 3] or [{f}, 3, 3] and viewmat [4, 4] or [{f}, 4, 4], got "
                f"{tuple(self.K.shape)} and {tuple(self.viewmat.shape)}"
            )
        if self.hand_depth is not None:
            hd = torch.as_tensor(self.hand_depth, dtype=torch.float32)
            if hd.shape != (f, 42):
                raise ValueError(f"hand_depth must be [{f}, 42], got {tuple(hd.shape)}")
            self.hand_depth = torch.nan_to_num(hd, nan=0.0, posinf=0.0, neginf=0.0)
        if self.pose_world is not None:
            pw = torch.as_tensor(self.pose_world, dtype=torch.float32)
            if pw.shape != (f, 33, 4):
                raise ValueError(f"pose_world must be [{f}, 33, 4], got {tuple(pw.shape)}")
            bad = ~torch.isfinite(pw).all(-1)
            pw = torch.where(bad[..., None], torch.zeros_like(pw), pw)
            self.pose_world = pw
        if self.face_mesh is not None:
            fm = torch.as_tensor(self.face_mesh, dtype=torch.float32)
            if fm.ndim != 3 or fm.shape[0] != f or fm.shape[2] != 3:
                raise ValueError(f"face_mesh must be [{f}, L, 3], got {tuple(fm.shape)}")
            ok = torch.isfinite(fm).all(-1) & (fm[..., 2] > 0)
            self.face_mesh = torch.where(ok[..., None], fm, torch.zeros_like(fm))
        if self.person_masks is not None:
            pm = torch.as_tensor(self.person_masks, dtype=torch.float32)
            if pm.ndim != 3 or pm.shape[0] != f:
                raise ValueError(f"person_masks must be [{f}, H, W], got {tuple(pm.shape)}")
            self.person_masks = torch.nan_to_num(pm, nan=1.0).clamp(0.0, 1.0)
        if self.face_depth is not None:
            fd = torch.as_tensor(self.face_depth, dtype=torch.float32)
            if self.face_mesh is None or fd.shape != self.face_mesh.shape[:2]:
                shape = tuple(fd.shape)
                raise ValueError(f"face_depth must be [F, L] beside face_mesh [F, L, 3], got {shape}")
            self.face_depth = torch.nan_to_num(fd, nan=0.0, posinf=0.0, neginf=0.0)

    @property
    def num_frames(self) -> int:
        return int(self.keypoints.shape[0])

    def frame_K(self) -> Tensor:
        """[F, 3, 3]."""
        return self.K.expand(self.num_frames, 3, 3) if self.K.ndim == 2 else self.K

    def frame_viewmat(self) -> Tensor:
        """[F, 4, 4]."""
        return self.viewmat.expand(self.num_frames, 4, 4) if self.viewmat.ndim == 2 else self.viewmat

    def person_scale(self) -> Tensor:
        """[F] person size in pixels, the unit of the 2D residuals: the diagonal of the confident
        pose points' box (the clip's median where a frame has too few), kept between 5% and 100%
        of the image diagonal (a close-up's off-image legs must not shrink the residuals)."""
        kp = self.keypoints[:, KEYPOINT_GROUPS["pose"]]
        ok = kp[..., 2] > 0.3
        big = torch.tensor(1e9)
        lo = torch.where(ok[..., None], kp[..., :2], big).amin(1)
        hi = torch.where(ok[..., None], kp[..., :2], -big).amax(1)
        diag = (hi - lo).norm(dim=-1)
        valid = ok.sum(1) >= 4
        image_diag = 2.0 * self.frame_K()[:, :2, 2].norm(dim=-1)  # principal point ~ image centre
        fallback = diag[valid].median() if valid.any() else image_diag
        return torch.minimum(torch.maximum(torch.where(valid, diag, fallback), 0.05 * image_diag), image_diag)


def keypoint_mask(n: int, indices) -> Tensor:
    """[n] 1 at ``indices`` (keypoint indices), else 0."""
    m = torch.zeros(n)
    m[list(indices)] = 1.0
    return m
