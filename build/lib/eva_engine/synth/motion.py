"""Sign-language-like motion for Anny, deterministic given a seed: arm raises, elbow bends, wrist
turns, a changing handshape per hand (open, fist, point, V, pinch, thumb up, claw, with
per-finger variation), facial actions (jawOpen, smiles, brows, blinks), small head and spine
movement, and a slow turn of the whole body.

Keyframes every ``keyframe_interval`` seconds, eased in and out (signs hold, then move), sampled
at any frame times. Joint axes come from the subject's rest skeleton (``body.rest_axes``: elbow
hinge, finger curl towards the palm), so the motion is anatomically plausible for any Anny
phenotype.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from eva_engine.body.params import BodyParams
from eva_engine.body.rest_axes import rest_axes

HANDSHAPES = {  # per-finger curl (thumb .. pinky), 0 = straight, 1 = fully bent
    "open": (0.0, 0.0, 0.0, 0.0, 0.0),
    "fist": (0.8, 1.0, 1.0, 1.0, 1.0),
    "point": (0.7, 0.0, 1.0, 1.0, 1.0),
    "v": (0.7, 0.0, 0.0, 1.0, 1.0),
    "pinch": (0.55, 0.55, 0.1, 0.05, 0.0),
    "thumb_up": (0.0, 1.0, 1.0, 1.0, 1.0),
    "claw": (0.4, 0.55, 0.55, 0.55, 0.55),
    "y": (0.0, 1.0, 1.0, 1.0, 0.0),
}
FACE_ACTIONS = (
    "jawOpen",
    "mouthSmileLeft",
    "mouthSmileRight",
    "browInnerUp",
    "mouthPucker",
    "eyeWideLeft",
    "eyeWideRight",
    "mouthFunnel",
    "browDownLeft",
    "browDownRight",
    "cheekPuff",
)
HELD_OUT_FACE_ACTIONS = ("mouthPucker", "mouthFunnel", "browDownLeft", "browDownRight", "cheekPuff")
"""Facial actions a benchmark can keep out of its training take, so test takes show new expressions."""


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """Ranges of the random motion (radians unless said otherwise)."""

    duration: float = 6.0
    """Seconds of motion; frames sample it evenly."""
    keyframe_interval: float = 0.75
    body_turn: float = 0.35
    """Amplitude of the slow whole-body turn (yaw), one left-right cycle over the clip."""
    arm_raise_probability: float = 0.15
    """Chance that a keyframe raises one arm high (above the shoulder)."""
    head_motion: float = 0.2
    blink_every: float = 1.8
    """Mean seconds between blinks."""
    face_actions: tuple[str, ...] = FACE_ACTIONS
    """The facial actions keyframes draw from (blinks come on top)."""


def _ease(x: np.ndarray) -> np.ndarray:
    return x * x * (3.0 - 2.0 * x)


def _keyframes(rng: np.random.Generator, k: int, cfg: MotionConfig, n_expr: int, expr_index: dict) -> dict:
    """Random keyframe values, arrays with k rows."""
    kf: dict[str, np.ndarray] = {}
    for s in "LR":
        raise_ = rng.random(k) < cfg.arm_raise_probability
        # Anny's rest arms already hang ~45 deg out, so signing space needs adduction.
        kf[f"flex.{s}"] = np.where(raise_, rng.uniform(1.6, 2.1, k), rng.uniform(0.2, 1.0, k))
        kf[f"abd.{s}"] = np.where(raise_, rng.uniform(-0.1, 0.2, k), rng.uniform(-0.7, 0.0, k))
        kf[f"elbow.{s}"] = np.where(raise_, rng.uniform(0.2, 0.8, k), rng.uniform(0.5, 1.8, k))
        kf[f"twist.{s}"] = rng.uniform(-1.1, 1.1, k)
        kf[f"wflex.{s}"] = rng.uniform(-0.5, 0.5, k)
        shapes = list(HANDSHAPES.values())
        curls = np.array([shapes[rng.integers(len(shapes))] for _ in range(k)])
        kf[f"curl.{s}"] = np.clip(curls + rng.normal(0, 0.08, curls.shape), 0, 1)
        kf[f"spread.{s}"] = rng.uniform(-0.15, 0.25, k)
    kf["head"] = rng.uniform(-cfg.head_motion, cfg.head_motion, (k, 3)) * (0.6, 1.0, 0.4)
    kf["spine"] = rng.uniform(-0.06, 0.06, (k, 3))
    expr = np.zeros((k, n_expr))
    for r in range(k):
        actions = list(cfg.face_actions)
        for name in rng.choice(actions, size=min(int(rng.integers(1, 4)), len(actions)), replace=False):
            expr[r, expr_index[name]] = rng.uniform(0.3, 0.9) if name != "jawOpen" else rng.uniform(0.2, 0.6)
        if "mouthSmileRight" in actions and expr[r, expr_index["mouthSmileLeft"]] > 0:  # mostly symmetric
            expr[r, expr_index["mouthSmileRight"]] = max(
                expr[r, expr_index["mouthSmileRight"]], expr[r, expr_index["mouthSmileLeft"]] * 0.8
            )
    kf["expression"] = expr
    return kf


def _interp(values: np.ndarray, times: np.ndarray, interval: float) -> np.ndarray:
    """Eased interpolation of keyframes [k, ...] at ``times`` [T] -> [T, ...]."""
    x = times / interval
    i = np.clip(np.floor(x).astype(int), 0, len(values) - 2)
    w = _ease(np.clip(x - i, 0.0, 1.0)).reshape(-1, *([1] * (values.ndim - 1)))
    return values[i] * (1 - w) + values[i + 1] * w


def sign_motion(
    model, shape: torch.Tensor, times: np.ndarray, seed: int, cfg: MotionConfig | None = None, take: int = 0
) -> BodyParams:
    """Body parameters [T] for frame ``times`` [T] (seconds in [0, duration]) of the subject with
    ``shape [1, S]``; deterministic given ``seed`` and ``take`` (another take is another motion
    of the same subject)."""
    cfg = cfg or MotionConfig()
    unknown = set(cfg.face_actions) - set(model.expression_names)
    if unknown or not cfg.face_actions:
        raise ValueError(
            f"face_actions must be non-empty expression names of the model; unknown: {sorted(unknown)}"
        )
    rng = np.random.default_rng([seed, 7, take])
    axes = rest_axes(model, shape)
    names = model.pose_joint_names
    jidx = {n: i for i, n in enumerate(names)}
    eidx = {n: i for i, n in enumerate(model.expression_names)}
    k = int(np.ceil(cfg.duration / cfg.keyframe_interval)) + 2
    kf = _keyframes(rng, k, cfg, len(model.expression_names), eidx)
    t = np.asarray(times, dtype=np.float64)
    n = len(t)
    joints = np.zeros((n, len(names), 3))

    def put(name: str, rotvec: np.ndarray) -> None:
        joints[:, jidx[name]] = rotvec

    def about(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
        return axis[None] * np.asarray(angle)[:, None]

    for s in "LR":
        sign = 1.0 if s == "L" else -1.0
        flex = _interp(kf[f"flex.{s}"], t, cfg.keyframe_interval)
        abd = _interp(kf[f"abd.{s}"], t, cfg.keyframe_interval)
        # Shoulder: raise forwards (about -X) after raising sideways (about +-Z).
        shoulder = Rotation.from_rotvec(about(np.array([-1.0, 0, 0]), flex)) * Rotation.from_rotvec(
            about(np.array([0, 0, sign]), abd)
        )
        put(f"upperarm01.{s}", shoulder.as_rotvec())
        put(f"lowerarm01.{s}", about(axes.elbow[s], _interp(kf[f"elbow.{s}"], t, cfg.keyframe_interval)))
        twist = _interp(kf[f"twist.{s}"], t, cfg.keyframe_interval)
        put(f"lowerarm02.{s}", about(axes.forearm[s], 0.5 * twist))
        wrist = Rotation.from_rotvec(about(axes.forearm[s], 0.5 * twist)) * Rotation.from_rotvec(
            about(axes.wrist_flex[s], _interp(kf[f"wflex.{s}"], t, cfg.keyframe_interval))
        )
        put(f"wrist.{s}", wrist.as_rotvec())
        curl = _interp(kf[f"curl.{s}"], t, cfg.keyframe_interval)  # [T, 5]
        spread = _interp(kf[f"spread.{s}"], t, cfg.keyframe_interval)
        for i in range(1, 6):
            c = curl[:, i - 1]
            gains = (0.5, 0.6, 0.5) if i == 1 else (1.3, 1.5, 0.9)
            fan = (i - 3) * 0.12 * spread * (0.0 if i == 1 else 1.0)
            base = Rotation.from_rotvec(about(axes.palm[s], fan * sign)) * Rotation.from_rotvec(
                about(axes.finger[s][i - 1], gains[0] * c)
            )
            put(f"finger{i}-1.{s}", base.as_rotvec())
            put(f"finger{i}-2.{s}", about(axes.finger[s][i - 1], gains[1] * c))
            put(f"finger{i}-3.{s}", about(axes.finger[s][i - 1], gains[2] * c))
    head = _interp(kf["head"], t, cfg.keyframe_interval)
    put("neck01", 0.4 * head)
    put("head", 0.6 * head)
    spine = _interp(kf["spine"], t, cfg.keyframe_interval)
    put("spine03", spine)
    put("spine01", 0.5 * spine)
    expression = np.clip(_interp(kf["expression"], t, cfg.keyframe_interval), 0.0, 1.0)
    # Blinks: short events at random times (a blink lasts ~0.25 s).
    blinks = np.cumsum(rng.exponential(cfg.blink_every, 16)) - 0.5 * cfg.blink_every
    for b in blinks:
        amount = np.clip(1.0 - np.abs(t - b) / 0.15, 0.0, 1.0)
        for name in ("eyeBlinkLeft", "eyeBlinkRight"):
            expression[:, eidx[name]] = np.maximum(expression[:, eidx[name]], amount)
    yaw = cfg.body_turn * np.sin(2 * np.pi * t / max(cfg.duration, 1e-6) + rng.uniform(-0.3, 0.3))
    root = np.stack([np.zeros(n), yaw, np.zeros(n)], axis=1)
    p = BodyParams(
        root_orient=torch.from_numpy(root),
        transl=torch.zeros(n, 3, dtype=torch.float64),
        joints=torch.from_numpy(joints),
        expression=torch.from_numpy(expression),
        shape=shape[:1].double().expand(n, -1).clone(),
    )
    return p.to(model.dtype)
