"""Hard videos with ground truth: the synthetic wild signer filmed badly (issue 41).

Each :class:`HardCase` changes one thing about the ``wild`` preset's clip (the same subject,
motion and renderer, ``synth.benchmark``) the way phone videos go wrong: a camera close to the
chest, a body partly out of frame, fast motion with motion blur, dark clothes on a dark
background, a second person walking past behind. :func:`render_hard_video` writes the clip as an
mp4, the way a user would upload it, and beside it the truth: each frame as it would look
filmed well (sharp, the subject alone) with its coverage mask, so an avatar trained through the
job path can be scored against what the person really looked like.

The refusal cases (``REFUSAL_CASES``) are videos a job must refuse rather than train on: a hand
alone, two people side by side throughout, a person too small to fit; :func:`nobody_video` is
the simplest, a clip with no person at all.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from eva_engine.body import load_body_model
from eva_engine.body.params import BodyParams
from eva_engine.data import write_video
from eva_engine.render.camera import intrinsics, look_at
from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer
from eva_engine.synth.benchmark import MOTION_SECONDS, PRESETS, random_shape
from eva_engine.synth.motion import FACE_ACTIONS, MotionConfig, sign_motion
from eva_engine.synth.texture import Look, bake_texture

DARK = (0.07, 0.07, 0.08)


@dataclasses.dataclass(frozen=True)
class HardCase:
    """One way of filming the signer. camera_target / distance / fov_y_deg: the camera (metres;
    the target's height is from the subject's nose in the first frame, as subjects differ in
    height by up to 0.4 m; None: the ``wild`` preset's); speed: motion played this many times faster;
    shutter_frames: the exposure as a share of the frame interval (0: sharp), rendered as the
    mean of ``blur_samples`` instants; dark: near-black clothes, hair and background;
    second_person: another person walks behind, across the frame, during the middle of the clip
    (``"behind"``) or stands beside the subject throughout (``"beside"``); track_hand: the camera
    follows the subject's right hand at ``distance`` (a hand alone)."""

    name: str
    description: str
    camera_target: tuple[float, float, float] | None = None
    distance: float | None = None
    fov_y_deg: float | None = None
    speed: float = 1.0
    shutter_frames: float = 0.0
    blur_samples: int = 1
    dark: bool = False
    second_person: str | None = None
    track_hand: bool = False


HARD_CASES: dict[str, HardCase] = {
    c.name: c
    for c in (
        HardCase("clean", "the wild signer as the benchmark films it (the reference)"),
        HardCase(
            "closeup",
            "chest up, 0.75 m from a wide lens: the hands come within 0.4 m of the camera",
            camera_target=(0.0, -0.05, 0.0),
            distance=0.75,
            fov_y_deg=62.0,
        ),
        HardCase(
            "cropped",
            "the body partly out of frame: one arm and the legs cut off",
            camera_target=(0.28, -0.19, 0.0),
            distance=1.5,
            fov_y_deg=30.0,
        ),
        HardCase(
            "blur",
            "fast motion (2.5x) with motion blur (a shutter open for the whole frame interval)",
            speed=2.5,
            shutter_frames=1.0,
            blur_samples=7,
        ),
        HardCase("dark", "dark clothes and hair on a dark background", dark=True),
        HardCase(
            "second_person",
            "a second person walks past behind the subject in the middle of the clip",
            second_person="behind",
        ),
    )
}
REFUSAL_CASES: dict[str, HardCase] = {
    c.name: c
    for c in (
        HardCase(
            "hand_alone", "a hand filling the frame, no body", distance=0.22, fov_y_deg=45.0, track_hand=True
        ),
        HardCase("two_people", "two people side by side throughout", distance=3.2, second_person="beside"),
        HardCase("too_small", "far away: about 60 px tall at 256 px", distance=12.0, fov_y_deg=30.0),
    )
}


def nobody_video(path: Path, frames: int = 8, size: int = 128, fps: float = 5.0) -> Path:
    """A valid clip that holds nobody (a grey ramp, ``size`` px square): it decodes fine, and a job
    on it must fail with a reason. Returns ``path``."""
    images = np.zeros((frames, size, size, 3), np.uint8)
    images[:] = np.linspace(0, 255, size, dtype=np.uint8)[None, None, :, None]
    return write_video(path, images, fps=fps)


@dataclasses.dataclass(frozen=True)
class HardVideo:
    """What :func:`render_hard_video` wrote: the clip, and per frame the truth image and mask."""

    video: Path
    truth_dir: Path
    times: list[float]
    fps: float

    def truth(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i`` as filmed well: RGB uint8 [H, W, 3] and coverage uint8 [H, W]."""
        import cv2

        rgb = cv2.imread(str(self.truth_dir / f"{i:06d}.png"), cv2.IMREAD_COLOR)[..., ::-1]
        mask = cv2.imread(str(self.truth_dir / f"{i:06d}_mask.png"), cv2.IMREAD_GRAYSCALE)
        return np.ascontiguousarray(rgb), mask

    @classmethod
    def load(cls, folder: str | Path) -> HardVideo:
        folder = Path(folder)
        info = json.loads((folder / "hard_video.json").read_text())
        return cls(folder / info["video"], folder / "truth", info["times"], info["fps"])


def _other_person(model, rng: np.random.Generator, n: int, seed: int) -> tuple[BodyParams, Look]:
    """Another subject's signing motion (seed + 1000), for the second person."""
    shape = random_shape(model, rng)
    times = np.linspace(0.0, MOTION_SECONDS, n)
    params = sign_motion(
        model, shape, times, seed + 1000, MotionConfig(duration=MOTION_SECONDS, face_actions=FACE_ACTIONS)
    )
    return params, Look.random(rng)


def _walk_behind(params: BodyParams, n: int) -> BodyParams:
    """The second person crossing from left to right 0.9 m behind, in the clip's middle 60%;
    elsewhere out of the frame."""
    t = torch.linspace(0.0, 1.0, n, dtype=params.transl.dtype)
    x = -2.2 + 4.4 * ((t - 0.2) / 0.6).clamp(0.0, 1.0)
    transl = params.transl.clone()
    transl[:, 0] = x
    transl[:, 2] = transl[:, 2] - 0.9
    return dataclasses.replace(params, transl=transl)


@dataclasses.dataclass(frozen=True)
class HardScene:
    """What a hard clip films: the subject's motion and the camera, frame by frame.

    params: BodyParams [F * S], S = ``shutter_instants`` per frame (frame-major), the sharp one at
    ``centre``; viewmat: [F, 4, 4] world-to-camera; K: [3, 3]; other: the second person's
    (BodyParams [F], Look) or None; times: [F] seconds."""

    case: HardCase
    params: BodyParams
    shutter_instants: int
    centre: int
    viewmat: torch.Tensor
    K: torch.Tensor
    look: Look
    other: tuple[BodyParams, Look] | None
    times: np.ndarray
    fps: float

    @property
    def sharp_params(self) -> BodyParams:
        """The pose of each frame's sharp instant, what the truth images show: BodyParams [F]."""
        return self.params[self.centre :: self.shutter_instants]


def hard_scene(
    case: HardCase | str, seed: int, *, frames: int = 60, size: int = 512, model=None
) -> HardScene:
    """The subject of ``seed``, its motion and the camera of ``case`` over ``frames`` frames of
    ``size`` px square: what :func:`render_hard_video` renders, and the truth a fit is measured
    against."""
    if isinstance(case, str):
        case = {**HARD_CASES, **REFUSAL_CASES}.get(case)
    if case is None:
        raise ValueError(f"unknown hard case; choose one of {sorted(HARD_CASES) + sorted(REFUSAL_CASES)}")
    if frames < 1 or size < 16:
        raise ValueError(f"frames must be >= 1 and size >= 16, got {frames} and {size}")
    if model is None:
        model = load_body_model("anny")
    wild = PRESETS["wild"]
    rng = np.random.default_rng([seed, 1])  # the benchmark's subject for this seed
    shape = random_shape(model, rng)
    look = Look.random(rng)
    if case.dark:
        look = dataclasses.replace(
            look, shirt=DARK, trousers=(0.05, 0.05, 0.06), hair=(0.04, 0.035, 0.03), shoes=DARK
        )
    fps = frames / MOTION_SECONDS
    times = np.arange(frames) / fps
    # Every instant the shutter sees: blur_samples per frame, centred on the frame's time.
    offsets = (
        np.linspace(-0.5, 0.5, case.blur_samples) * case.shutter_frames / fps
        if case.blur_samples > 1
        else np.zeros(1)
    )
    # A faster clip plays a longer motion (speed x 6 s) in the same 6 s.
    duration = MOTION_SECONDS * case.speed
    instants = ((times[:, None] + offsets[None, :]) * case.speed).clip(0.0, duration)
    motion_cfg = MotionConfig(duration=duration, body_turn=wild.body_turn, face_actions=FACE_ACTIONS)
    params = sign_motion(model, shape, instants.reshape(-1), seed, motion_cfg)
    centre = case.blur_samples // 2 if case.blur_samples > 1 else 0
    other = None
    if case.second_person is not None:
        other_params, other_look = _other_person(model, np.random.default_rng([seed, 2]), frames, seed)
        if case.second_person == "behind":
            other_params = _walk_behind(other_params, frames)
        else:  # "beside": the subject 0.45 m to the left, the other 0.45 m to the right
            shift = torch.tensor([0.45, 0.0, 0.0], dtype=params.transl.dtype)
            params = dataclasses.replace(params, transl=params.transl - shift)
            other_params = dataclasses.replace(other_params, transl=other_params.transl + shift)
        other = (other_params, other_look)
    with torch.no_grad():
        keypoints = model.keypoints(model(params[centre :: len(offsets)]))  # [F, K, 3]
    if case.track_hand:
        hand = [
            i
            for i, n in enumerate(model.keypoint_names)
            if n in ("right_hand_wrist", "right_hand_middle_finger_mcp", "right_hand_index_finger_pip")
        ]
        targets = keypoints[:, hand].mean(dim=1).numpy()
    elif case.camera_target is not None:  # relative to the subject's nose: subjects differ in height
        nose_y = float(keypoints[0, model.keypoint_names.index("nose"), 1])
        x, dy, z = case.camera_target
        targets = np.tile(np.array([x, nose_y + dy, z]), (frames, 1))
    else:
        targets = np.tile(np.asarray(wild.camera_target), (frames, 1))
    distance = case.distance or wild.distance
    viewmat = torch.stack(
        [
            torch.as_tensor(look_at(t + np.array([0.0, 0.0, distance]), t), dtype=torch.float32)
            for t in targets
        ]
    )
    K = torch.as_tensor(intrinsics(size, size, case.fov_y_deg or wild.fov_y_deg), dtype=torch.float32)
    return HardScene(case, params, len(offsets), centre, viewmat, K, look, other, times, fps)


def render_hard_video(
    case: HardCase | str,
    seed: int,
    out: str | Path,
    *,
    frames: int = 60,
    size: int = 512,
    model=None,
    supersample: int = 2,
    texture_size: int = 1024,
) -> HardVideo:
    """Render ``frames`` frames (6 s of motion, ``size`` px square) of the signer of ``seed`` filmed
    as ``case`` says (:func:`hard_scene`); write ``out/video.mp4``, ``out/truth/{i:06d}.png`` /
    ``_mask.png`` and ``out/hard_video.json``."""
    import cv2

    if model is None:
        model = load_body_model("anny")
    scene = hard_scene(case, seed, frames=frames, size=size, model=model)
    case, params, other, look, fps = scene.case, scene.params, scene.other, scene.look, scene.fps
    samples, centre = scene.shutter_instants, scene.centre
    out = Path(out)
    truth_dir = out / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    background = DARK if case.dark else (1.0, 1.0, 1.0)
    config = MeshRenderConfig(
        width=size,
        height=size,
        supersample=supersample,
        background=background,
        light=PRESETS["wild"].light,
        light_frame="world",
    )
    with torch.no_grad():
        posed = model(params).vertices.reshape(frames, samples, -1, 3)
        other_verts = model(other[0]).vertices if other is not None else None
    bg = torch.tensor(background, dtype=torch.float32)
    video_frames = []
    with MeshRenderer(model.faces, config, num_vertices=model.num_vertices) as renderer:
        # One GL context: the second person's texture is swapped in for its render.
        atlas = {
            "uv": model.anny.texture_coordinates.cpu().numpy(),
            "face_uv": model.anny.face_texture_coordinate_indices.cpu().numpy(),
        }
        textures = [bake_texture(model, params[0], look, renderer, texture_size, seed=seed)]
        if other is not None:
            textures.append(
                bake_texture(model, other[0][0], other[1], renderer, texture_size, seed=seed + 1000)
            )
        renderer.set_surface(texture=textures[0], **atlas)
        for i in range(frames):
            viewmat, K = scene.viewmat[i], scene.K
            shots = [renderer.render(posed[i, k], viewmat, K) for k in range(samples)]
            sharp = shots[centre]
            rgb = torch.stack([s.rgb for s in shots]).mean(0)
            if other is not None:
                renderer.set_surface(texture=textures[1], **atlas)
                s2 = renderer.render(other_verts[i], viewmat, K)
                renderer.set_surface(texture=textures[0], **atlas)
                # Both renders carry the background where uncovered; the nearer surface goes over.
                a1 = torch.stack([s.alpha for s in shots]).mean(0)[..., None]
                a2 = s2.alpha[..., None]
                front = ((s2.alpha > 0) & ((sharp.depth <= 0) | (s2.depth < sharp.depth)))[..., None]
                rgb = torch.where(front, s2.rgb + (1 - a2) * (rgb - bg), rgb + (1 - a1) * (s2.rgb - bg))
            video_frames.append((rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
            truth = (sharp.rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(truth_dir / f"{i:06d}.png"), truth[..., ::-1])
            mask = (sharp.alpha.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(truth_dir / f"{i:06d}_mask.png"), mask)
    video = write_video(out / "video.mp4", np.stack(video_frames), fps=fps)
    info = {
        "case": dataclasses.asdict(case),
        "seed": seed,
        "frames": frames,
        "size": size,
        "fps": fps,
        "times": [float(t) for t in scene.times],
        "video": video.name,
        "look": dataclasses.asdict(look),
        "generator": "eva_engine.synth.hard",
    }
    (out / "hard_video.json").write_text(json.dumps(info, indent=1))
    return HardVideo(video, truth_dir, info["times"], fps)
