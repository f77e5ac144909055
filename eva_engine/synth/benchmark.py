"""The synthetic benchmark: a textured Anny subject signing in front of a static camera, rendered
by a triangle-mesh rasterizer (``eva_engine.render.mesh``, not Gaussians), written in the
dataset layout with ground truth, per-hand and face region masks included.

Presets (modelled on the paper's data):

- ``controlled`` (XHumans-like): the subject from the thighs up (so hands are ~60-70 px long at
  512 px), a slow whole-body turn; ground-truth parameters and keypoints are given to the
  pipeline. Split as XHumans: the avatar trains on one motion take and is tested on other takes
  of the same subject (20 frames each, every 5th frame), whose motions, hand shapes and facial
  expressions it has never seen (the training take draws from a subset of the facial actions,
  the test takes from all of them).
- ``wild`` (UPB-like): a waist-up signer; the pipeline gets only images (it must detect and
  align); the ground truth is kept under ``ground_truth/`` for evaluation. Split as UPB:
  alternate frames of one take train and test.
- ``wild-gt`` (the paper's regime, ``bench/paper_regime.py``): ``wild``'s subject, framing and
  split with the ground-truth parameters given, as the paper trains on UPB's fitted parameters:
  only the avatar is measured, not the alignment.
- ``novel`` (novel poses and views): ``controlled``'s subject, framing and ground truth, but the
  training take keeps both arms below the shoulders, so the test splits can go beyond it:
  ``test_pose`` ("near": other takes of the same generator), ``test_far_pose`` ("far": a take that
  raises the arms above the shoulders), ``test_view`` (training poses from 35 and 70 deg) and
  ``test_far_view`` (far poses from 35 deg). ``extra["novelty"]`` records, per test frame, how
  far its pose is from the nearest training pose and where its camera is relative to the body
  (``novelty``).

Appearance: a procedural albedo and gloss texture (``synth.texture``) with millimetre-scale
detail on the hands, face and clothing, lit by a light fixed in the world with Lambert diffuse and a
Blinn-Phong highlight, so shading changes with the pose and with the view. ``test_view`` frames
show training poses from a camera turned 35 deg (``novel``: and 70 deg) about the subject.
Everything is deterministic given the seed (which picks the subject and its motions).

Sizes: ``tiny`` (96 px, for tests), ``small`` (256 px, large enough for MediaPipe) and ``bench``
(512 px, 150 training frames).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from eva_engine.body.params import BodyParams
from eva_engine.data.dataset import DatasetMeta, DatasetWriter, ParamNames
from eva_engine.data.region_masks import coverage_by_region, face_regions
from eva_engine.geometry import project_points, to_camera
from eva_engine.progress import Progress, ProgressEvent
from eva_engine.render.camera import intrinsics, look_at
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer
from eva_engine.synth.motion import FACE_ACTIONS, HELD_OUT_FACE_ACTIONS, MotionConfig, sign_motion
from eva_engine.synth.texture import Look, apply_look

SPLIT_STYLES = ("takes", "interleaved", "novel")


@dataclasses.dataclass(frozen=True)
class Preset:
    """What the scene shows and what the pipeline is given."""

    name: str
    camera_target: tuple[float, float, float]
    """Point the camera looks at (world, metres)."""
    distance: float
    fov_y_deg: float
    body_turn: float
    """Amplitude (radians) of the slow whole-body turn."""
    give_ground_truth: bool
    """Write the ground-truth parameters and keypoints as pipeline inputs too."""
    split: str
    """"takes" (train on one take, test on others: XHumans), "interleaved" (alternate frames
    of one take: UPB) or "novel" (takes, plus a take beyond the training range: module
    docstring)."""
    view_angles_deg: tuple[float, ...] = (35.0,)
    """The held-out cameras, turned about the vertical axis through the target."""
    arm_raise_probability: float = MotionConfig.arm_raise_probability
    """Chance that a keyframe of the training take (and of the "near" test takes) raises an arm
    above the shoulder."""
    far_arm_raise_probability: float = 0.9
    """The same for the "novel" split's far take."""
    light: tuple[float, float, float] = (-0.35, 0.55, 1.0)
    """Direction towards the light in the world (above, in front, to the subject's right)."""


@dataclasses.dataclass(frozen=True)
class Size:
    """Resolution and length."""

    name: str
    image_size: int
    num_frames: int
    """Frames of the training take (6 s of motion)."""
    num_view_frames: int
    supersample: int
    texture_size: int
    test_takes: int = 1
    """"takes" split: number of test takes ..."""
    test_frames: int = 3
    """... frames sampled from each ..."""
    test_stride: int = 1
    """... every this many frames (at the training take's frame rate)."""
    test_every: int = 2
    """"interleaved" split: every this many frames (the second of each group) is a test frame."""


# Keyed by the names of ``eva_engine.synth_names`` (the CLI's choices), in its order.
PRESETS: dict[str, Preset] = {
    "controlled": Preset(
        "controlled", (0.0, 0.22, 0.0), 2.0, 40.0, body_turn=0.5, give_ground_truth=True, split="takes"
    ),
    "wild": Preset(
        "wild", (0.0, 0.42, 0.0), 2.45, 30.0, body_turn=0.15, give_ground_truth=False, split="interleaved"
    ),
    "wild-gt": Preset(
        "wild-gt", (0.0, 0.42, 0.0), 2.45, 30.0, body_turn=0.15, give_ground_truth=True, split="interleaved"
    ),
    "novel": Preset(
        "novel",
        (0.0, 0.22, 0.0),
        2.0,
        40.0,
        body_turn=0.5,
        give_ground_truth=True,
        split="novel",
        view_angles_deg=(35.0, 70.0),
        arm_raise_probability=0.0,
    ),
}
SIZES: dict[str, Size] = {
    "tiny": Size("tiny", 96, 12, 3, supersample=3, texture_size=512),
    # Large enough for a real detector (MediaPipe needs ~15 px palms), small enough for tests.
    "small": Size("small", 256, 12, 3, supersample=2, texture_size=1024, test_frames=4),
    # XHumans' protocol: 20 frames of each test take, sampled every 5th frame.
    "bench": Size(
        "bench", 512, 150, 30, supersample=2, texture_size=2048, test_takes=2, test_frames=20, test_stride=5
    ),
}
MOTION_SECONDS = 6.0
GENERATOR = "eva_engine.synth.benchmark"
"""``extra["generator"]`` of the datasets this module writes."""
TRAIN_FACE_ACTIONS = tuple(a for a in FACE_ACTIONS if a not in HELD_OUT_FACE_ACTIONS)


@dataclasses.dataclass(frozen=True)
class Shot:
    """One dataset frame: motion ``take`` at ``time`` seconds, seen by the camera turned
    ``view_deg`` about the subject (0: the training camera)."""

    take: int
    time: float
    view_deg: float = 0.0


@dataclasses.dataclass(frozen=True)
class Layout:
    """Which motion sample every dataset frame shows. frames: one ``Shot`` per frame; splits:
    the dataset's splits; pose_of_frame: per frame, the frame whose motion sample it shows (itself,
    or for a held-out view, the frame it sees again from elsewhere)."""

    frames: list[Shot]
    splits: dict[str, list[int]]
    pose_of_frame: list[int]


def layout(preset: Preset, size: Size) -> Layout:
    """The frames and splits of ``preset`` at ``size`` (module docstring)."""
    fps = size.num_frames / MOTION_SECONDS
    shots = [Shot(0, i / fps) for i in range(size.num_frames)]

    def add_take(take: int) -> list[int]:
        ids = list(range(len(shots), len(shots) + size.test_frames))
        shots.extend(Shot(take, j * size.test_stride / fps) for j in range(size.test_frames))
        return ids

    far: list[int] = []
    if preset.split in ("takes", "novel"):
        train = list(range(len(shots)))
        test = [i for take in range(1, size.test_takes + 1) for i in add_take(take)]
        if preset.split == "novel":
            far = add_take(size.test_takes + 1)
    elif preset.split == "interleaved":
        test = [i for i in range(len(shots)) if i % size.test_every == size.test_every - 1]
        train = [i for i in range(len(shots)) if i % size.test_every != size.test_every - 1]
    else:
        raise ValueError(f"unknown split style {preset.split!r}; choose one of {SPLIT_STYLES}")
    pose_of = list(range(len(shots)))

    def views(sources: list[int], count: int, angle: float) -> list[int]:
        picks = np.linspace(0, len(sources) - 1, count).round().astype(int) if count else []
        ids = []
        for k in picks:
            src = sources[k]
            ids.append(len(shots))
            shots.append(dataclasses.replace(shots[src], view_deg=angle))
            pose_of.append(src)
        return ids

    per_angle = size.num_view_frames // len(preset.view_angles_deg)
    test_view = [i for a in preset.view_angles_deg for i in views(train, per_angle, a)]
    splits = {"train": train, "test_pose": test, "test_view": test_view}
    if preset.split == "novel":
        splits["test_far_pose"] = far
        splits["test_far_view"] = views(far, max(len(far) // 2, 1), preset.view_angles_deg[0])
    return Layout(shots, splits, pose_of)


def take_motion(
    model,
    shape: torch.Tensor,
    preset: Preset,
    seed: int,
    take: int,
    times: list[float],
    far_take: int | None = None,
) -> tuple[BodyParams, dict]:
    """Body parameters [T] at ``times`` of motion ``take``, and its settings. The training take
    of a "takes" or "novel" preset keeps the held-out facial actions out; every other take draws
    from all. A "novel" preset's far take (``far_take``) raises the arms more often."""
    held_out = preset.split in ("takes", "novel") and take == 0
    actions = TRAIN_FACE_ACTIONS if held_out else FACE_ACTIONS
    far = preset.split == "novel" and take == far_take
    cfg = MotionConfig(
        duration=MOTION_SECONDS,
        body_turn=preset.body_turn,
        face_actions=actions,
        arm_raise_probability=preset.far_arm_raise_probability if far else preset.arm_raise_probability,
    )
    times_ = np.asarray(times, dtype=np.float64)
    return sign_motion(model, shape, times_, seed, cfg, take=take), dataclasses.asdict(cfg)


def cameras(preset: Preset, size: Size, view_deg: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """K [3, 3] and the viewmat [4, 4] of the camera turned ``view_deg`` about the vertical axis
    through the target from the training camera (0: the training camera)."""
    target = np.asarray(preset.camera_target)
    a = math.radians(view_deg)
    eye = target + preset.distance * np.array([math.sin(a), 0.0, math.cos(a)])
    return intrinsics(size.image_size, size.image_size, preset.fov_y_deg), look_at(eye, target)


def novelty(model, params: BodyParams, viewmats: torch.Tensor, train: list[int], test: list[int]) -> dict:
    """{frame: {"pose_deg", "nearest_train", "yaw_deg", "pitch_deg"}} for the ``test`` frames:
    the largest joint angle to the nearest training pose (body joints, the fingers left out), that
    pose's frame, and the camera's direction seen from the body (``avatar.coverage``)."""
    from eva_engine.avatar.coverage import nearest_pose_distance, rest_root, view_angles

    body_joints = model.joint_part_ids[1:] == 0
    joints = params.joints.double()
    dist, nearest = nearest_pose_distance(joints[test], joints[train], body_joints)
    yaw, pitch = view_angles(params[test], viewmats[test], rest_root(model, params.shape[:1]))
    return {
        int(i): {
            "pose_deg": round(math.degrees(float(dist[k])), 2),
            "nearest_train": int(train[int(nearest[k])]),
            "yaw_deg": round(float(yaw[k]), 2),
            "pitch_deg": round(float(pitch[k]), 2),
        }
        for k, i in enumerate(test)
    }


def random_shape(model, rng: np.random.Generator) -> torch.Tensor:
    """An adult Anny phenotype [1, S] (gender, age, muscle, weight, height, proportions)."""
    ranges = {
        "gender": (0.0, 1.0),
        "age": (0.45, 0.75),
        "muscle": (0.3, 0.7),
        "weight": (0.3, 0.7),
        "height": (0.3, 0.7),
        "proportions": (0.4, 0.6),
    }
    values = [rng.uniform(*ranges.get(name, (0.45, 0.55))) for name in model.shape_names]
    return torch.tensor([values], dtype=model.dtype)


def generate(
    preset: str,
    size: str,
    seed: int,
    out: str | Path,
    *,
    model=None,
    overwrite: bool = False,
    progress: Progress | None = None,
) -> Path:
    """Render a synthetic dataset into ``out`` (the layout of ``docs/dataset-format.md``) and
    return its path. ``model``: an Anny body model (loaded if None); ``progress`` hears stage
    "render" after every frame."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {list(PRESETS)}")
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r}; choose one of {list(SIZES)}")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if model is None:
        from eva_engine.body import load_body_model

        model = load_body_model("anny")
    if model.name != "anny":
        raise ValueError(f"the synthetic benchmark renders Anny, got body model {model.name!r}")
    p, s = PRESETS[preset], SIZES[size]
    plan = layout(p, s)
    fps = s.num_frames / MOTION_SECONDS
    rng = np.random.default_rng([seed, 1])
    shape = random_shape(model, rng)
    look = Look.random(rng)
    K, _ = cameras(p, s)
    meta = DatasetMeta(
        source="synthetic",
        fps=fps,
        image_size=(s.image_size, s.image_size),
        name=f"{preset}-{size}-seed{seed}",
        body_model="anny",
        background=(1.0, 1.0, 1.0),
        camera_source="ground_truth",
    )
    # Each take's motion at its frames' times, then every frame's row in the plan's order.
    far_take = s.test_takes + 1 if p.split == "novel" else None
    motions, rows = {}, {}
    for take in sorted({shot.take for shot in plan.frames}):
        times = [shot.time for shot in plan.frames if shot.take == take]
        rows[take], motions[take] = take_motion(model, shape, p, seed, take, times, far_take)
    seen = dict.fromkeys(rows, 0)
    frame_rows = []
    for shot in plan.frames:
        frame_rows.append(rows[shot.take][seen[shot.take]])
        seen[shot.take] += 1
    params = BodyParams.cat(frame_rows)
    views = [cameras(p, s, shot.view_deg)[1] for shot in plan.frames]
    viewmats = torch.stack(views)
    tested = [i for name, ids in plan.splits.items() if name != "train" for i in ids]
    with DatasetWriter(out, meta, overwrite=overwrite) as writer:
        with torch.no_grad():
            posed = model(params)
            keypoints3d = model.keypoints(posed)
        cam = to_camera(keypoints3d, viewmats.to(keypoints3d.dtype))
        uv, depth = project_points(cam, K.to(keypoints3d.dtype)), cam[..., 2]
        h = w = s.image_size
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h) & (depth > 0)
        keypoints = torch.cat([uv, inside[..., None].to(uv.dtype)], dim=-1).float()
        regions = face_regions(model)
        config = MeshRenderConfig(
            width=w,
            height=h,
            supersample=s.supersample,
            background=(1.0, 1.0, 1.0),
            light=p.light,
            light_frame="world",
        )
        with MeshRenderer(model.faces, config, num_vertices=model.num_vertices) as renderer:
            apply_look(renderer, model, params[0], look, s.texture_size, seed=seed)
            total = len(plan.frames)
            for i, shot in enumerate(plan.frames):
                r = renderer.render(posed.vertices[i], views[i], K)
                writer.add_frame(
                    r.rgb.numpy(),
                    r.alpha.numpy(),
                    K=K,
                    viewmat=views[i],
                    time=float(shot.time),
                    regions=coverage_by_region(r, regions),
                )
                if progress is not None:
                    progress(ProgressEvent("render", i + 1, total, f"rendering frame {i + 1}/{total}"))
        give = p.give_ground_truth
        return writer.finish(
            plan.splits,
            params=params if give else None,
            params_names=ParamNames.of(model),
            params_source="ground_truth",
            keypoints=keypoints if give else None,
            keypoint_names=list(model.keypoint_names),
            keypoints_source="ground_truth",
            gt_params=params,
            gt_keypoints=keypoints,
            extra={
                "generator": GENERATOR,
                "preset": preset,
                "size": size,
                "seed": seed,
                "split_style": p.split,
                "take_of_frame": [shot.take for shot in plan.frames],
                "pose_of_frame": plan.pose_of_frame,
                "view_deg_of_frame": [shot.view_deg for shot in plan.frames],
                "look": dataclasses.asdict(look),
                "view_angle_deg": p.view_angles_deg[0],
                "view_angles_deg": list(p.view_angles_deg),
                "novelty": novelty(model, params, viewmats, plan.splits["train"], tested),
                "motion": [motions[k] for k in sorted(motions)],
                "held_out_face_actions": list(HELD_OUT_FACE_ACTIONS) if p.split != "interleaved" else [],
                "renderer": "moderngl/llvmpipe textured mesh, Lambert + Blinn-Phong, world light",
                "supersample": s.supersample,
            },
        )
