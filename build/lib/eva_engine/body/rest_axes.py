"""Anatomical rotation axes of one subject's rest skeleton, in world axes: the upper arm's and the
forearm's twist, the elbow's hinge, the palm's normal, the wrist's flexion and each finger's
curl. A rotation about them bends a joint the way the body bends, for any phenotype; the pose
controls (sliders), the synthetic benchmark's signing motion and the fit's body prior are built
on them. The joints are Anny's (``lowerarm01.L``, ``finger2-1.R``, ...).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from eva_engine.body.model import BodyModel


@dataclasses.dataclass
class RestAxes:
    """Unit axes [3] (world) per side ``L``/``R``. A positive angle about ``elbow`` flexes it,
    about a ``finger`` axis curls that finger towards the palm."""

    elbow: dict[str, np.ndarray]
    forearm: dict[str, np.ndarray]
    """The forearm's direction, elbow to wrist (its twist axis)."""
    upper_arm: dict[str, np.ndarray]
    """The upper arm's direction, shoulder to elbow (its twist axis)."""
    palm: dict[str, np.ndarray]
    """The palm's normal, out of the palm."""
    finger: dict[str, list[np.ndarray]]
    """Curl axis per finger, thumb .. pinky."""
    wrist_flex: dict[str, np.ndarray]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def rest_axes(model: BodyModel, shape: torch.Tensor) -> RestAxes:
    """The axes of the subject with ``shape [1, S]`` in its rest pose."""
    with torch.no_grad():
        p = model.default_params(1)
        p.shape = shape[:1].to(p.shape)
        out = model(p)
        kp = model.keypoints(out)[0].double().numpy()
    j = {n: out.joints[0, i].double().numpy() for i, n in enumerate(model.joint_names)}
    names = list(model.keypoint_names)
    axes = RestAxes({}, {}, {}, {}, {}, {})
    for s, side in (("L", "left"), ("R", "right")):
        upper = _unit(j[f"lowerarm01.{s}"] - j[f"upperarm01.{s}"])
        fore = _unit(j[f"wrist.{s}"] - j[f"lowerarm01.{s}"])
        axes.elbow[s] = _unit(np.cross(upper, fore))  # + angle = more flexion
        axes.forearm[s] = fore
        axes.upper_arm[s] = upper
        w, a, b, m = (j[f"{x}.{s}"] for x in ("wrist", "finger2-1", "finger5-1", "finger3-1"))
        n = _unit(np.cross(a - w, b - w))
        tip = kp[names.index(f"{side}_hand_middle_finger_tip")]
        palm = n * np.sign(np.dot(tip - m, n))  # rest fingers curl slightly towards the palm
        axes.palm[s] = palm
        axes.wrist_flex[s] = _unit(np.cross(_unit(m - w), palm))
        axes.finger[s] = []
        for i in range(1, 6):
            d = _unit(j[f"finger{i}-3.{s}"] - j[f"finger{i}-1.{s}"])
            axes.finger[s].append(_unit(np.cross(d, palm)))  # + angle curls towards the palm
    return axes
