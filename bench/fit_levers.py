"""The fit against the truth on the hard clips (issue 41): how far each fit variant puts the body.

``bench/closeup_levers.py`` found that the close-up's avatar is limited by its fit: trained and
scored with the poses and camera the clip was rendered with, its held-out LPIPS-VGG falls by
two thirds. This script measures the fit alone, without training, on every hard case of
``eva_engine.synth.hard`` (the clip of ``seed``, 40 frames of 512 px, as ``bench/hard_inputs.py``
renders it), for the fit variants of ``closeup_levers.VARIANTS`` that change the fit:

- *fit IoU*: the fitted body's silhouette against the true person mask, mean over the frames;
- *joint error*: fitted against true keypoints, projected (px, mean over the frames; the
  truth through the true camera, the fit through the guessed one), per group;
- *skin error*: fitted against true projections of the same vertices, px, per part (the
  vertices each bone moves most: torso, upper arm, forearm; those in the frame), median over the
  part, mean over the frames; and the torso's *slide*: the frame-to-frame spread (std over the
  frames, norm of x and y) of the torso's mean offset. A constant offset (a fitted shape unlike
  the true one) an avatar absorbs; a slide smears what is drawn on the skin;
- *fit (s)*: the fit's time on 1 thread.

And what MediaPipe's 3D world landmarks (the fit's 3D term) get wrong: the angle between their
upper arms and forearms and the true ones, per case, beside the hips' visibility (MediaPipe's
world skeleton is centred on the hips, which a close-up leaves out of frame).

    .venv/bin/python -m bench fit_levers --seed 0 [--cases ...] [--variants ...]   # run (claims)
    .venv/bin/python -m bench fit_levers --report [--name NAME]                  # gather
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bench.closeup_levers import VARIANTS, fit_iou, preprocess_config
from bench.hard_inputs import FRAMES, SIZE, claim
from bench.machine import describe, header_line, run_header, write_result

ROOT = Path(__file__).resolve().parents[1]
FIT_VARIANTS = ("baseline", "true_fov", "outline_longer", "outline_longer_no_3d", "body_prior")
SKIN_PARTS = {
    "torso": ("spine", "clavicle", "shoulder"),
    "upper arm": ("upperarm",),
    "forearm": ("lowerarm",),
}
JOINT_GROUPS = {
    "head": ("nose", "left_eye", "right_eye"),
    "shoulders": ("left_shoulder", "right_shoulder"),
    "elbows": ("left_elbow", "right_elbow"),
    "wrists": ("left_hand_wrist", "right_hand_wrist"),
}
SKIN_COLUMNS = (*SKIN_PARTS, "torso slide")
ARMS = {"upper arm": ("shoulder", "elbow"), "forearm": ("elbow", "wrist")}


def clip_and_detections(case: str, seed: int, work: Path, model):
    """The clip (rendered once) and its decoded frames' detections (cached in the work folder)."""
    from eva_engine.align.preprocess import detect_frames
    from eva_engine.data.video import read_video
    from eva_engine.synth.hard import HardVideo, render_hard_video

    folder = work / "fit_levers" / f"{case}_s{seed}"
    if (folder / "clip" / "hard_video.json").is_file():
        hv = HardVideo.load(folder / "clip")
    else:
        hv = render_hard_video(case, seed, folder / "clip", frames=FRAMES, size=SIZE, model=model)
    config = preprocess_config(VARIANTS["baseline"])
    clip = read_video(hv.video, config.read_options(config.max_frames, config.max_size))
    cache = folder / "detections.pkl"
    if cache.is_file():
        det = pickle.loads(cache.read_bytes())
    else:
        det = detect_frames(iter(clip.frames), config.detector)
        cache.write_bytes(pickle.dumps(det))
    return hv, clip, det


def projected_keypoints(model, params, viewmat, K) -> torch.Tensor:
    """[F, K, 2] the model's keypoints in pixels. viewmat: [F, 4, 4] or [4, 4]; K: [3, 3]."""
    from eva_engine.geometry import project_points, to_camera

    with torch.no_grad():
        kp = model.keypoints(model(params))
    return project_points(to_camera(kp, viewmat), K)


def skin_errors(model, fitted, fit_view, fit_K, truth, true_view, true_K, size: int) -> dict:
    """Per part of ``SKIN_PARTS``: the fitted and true projections of its vertices compared
    (module docstring); ``"torso slide"``: the spread of the torso's mean offset over the frames.
    fitted / truth: BodyParams [F]; *_view: [F, 4, 4]; *_K: [3, 3]."""
    from eva_engine.geometry import project_points, to_camera

    with torch.no_grad():
        uv_fit = project_points(to_camera(model(fitted).vertices, fit_view), fit_K)
        uv_true = project_points(to_camera(model(truth).vertices, true_view), true_K)
    bones = model.skinning_weights.argmax(dim=1).tolist()
    names = model.joint_names
    seen = ((uv_true >= 0) & (uv_true < size)).all(-1)  # [F, V]
    out = {}
    for part, prefixes in SKIN_PARTS.items():
        mine = torch.tensor([names[b].startswith(prefixes) for b in bones])
        per_frame, offsets = [], []
        for f in range(len(uv_fit)):
            m = mine & seen[f]
            if int(m.sum()) < 20:
                continue
            d = uv_fit[f, m] - uv_true[f, m]
            per_frame.append(float(d.norm(dim=-1).median()))
            offsets.append(d.mean(0))
        out[part] = float(np.mean(per_frame)) if per_frame else float("nan")
        if part == "torso" and len(offsets) > 1:
            out["torso slide"] = float(torch.stack(offsets).std(0).norm())
    return out


def run_fit(case: str, seed: int, name: str, work: Path, model) -> dict:
    from eva_engine.align.camera import guess_camera
    from eva_engine.align.clip import fit_clip
    from eva_engine.body import KEYPOINT_NAMES
    from eva_engine.synth.hard import hard_scene

    hv, clip, det = clip_and_detections(case, seed, work, model)
    config = preprocess_config(VARIANTS[name])
    h, w = clip.frames.shape[1:3]
    K, viewmat = guess_camera(w, h, config.fov_y_deg)
    start = time.perf_counter()
    fit = fit_clip(model, det.targets(K, viewmat), torch.as_tensor(clip.timestamps), config.fitting)
    seconds = time.perf_counter() - start
    scene = hard_scene(case, seed, frames=len(hv.times), size=w, model=model)
    fitted = projected_keypoints(model, fit.params, viewmat, K)
    true = projected_keypoints(model, scene.sharp_params, scene.viewmat, scene.K)
    errors = {
        group: float((fitted[:, idx] - true[:, idx]).norm(dim=-1).mean())
        for group, names in JOINT_GROUPS.items()
        for idx in [[KEYPOINT_NAMES.index(n) for n in names]]
    }
    n = len(clip.timestamps)
    skin = skin_errors(
        model, fit.params, viewmat.expand(n, 4, 4), K, scene.sharp_params, scene.viewmat, scene.K, w
    )
    frames = _FitFrames(
        fit.params, viewmat.expand(n, 4, 4), K.expand(n, 3, 3), torch.as_tensor(clip.timestamps), (h, w)
    )
    ious = fit_iou(model, frames, hv)
    return {
        "case": case,
        "seed": seed,
        "variant": name,
        "fit_iou": float(np.mean(ious)),
        "joint_error_px": errors,
        "skin_error_px": skin,
        "fit_s": seconds,
    }


@dataclass
class _FitFrames:
    """What ``closeup_levers.fit_iou`` reads of a dataset, from a fit in memory: params [F],
    viewmat [F, 4, 4], K [F, 3, 3], timestamps [F] seconds, image_size (H, W)."""

    params: object
    viewmat: torch.Tensor
    K: torch.Tensor
    timestamps: torch.Tensor
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.viewmat)


def world_landmark_errors(case: str, seed: int, work: Path, model) -> dict:
    """Angles (degrees, median over the frames) between MediaPipe's 3D upper arms and forearms
    and the true ones, in the camera's axes; the hips' mean visibility."""
    from eva_engine.body import KEYPOINT_NAMES
    from eva_engine.geometry import to_camera
    from eva_engine.synth.hard import hard_scene

    hv, clip, det = clip_and_detections(case, seed, work, model)
    scene = hard_scene(case, seed, frames=len(hv.times), size=clip.frames.shape[2], model=model)
    with torch.no_grad():
        kp = model.keypoints(model(scene.sharp_params))
    cam = to_camera(kp, scene.viewmat).numpy()
    world = det.pose_world  # [F, 33, 4], x right, y down, z away: the camera's axes
    angles = {}
    for bone, (a, b) in ARMS.items():
        per_side = []
        for side in ("left", "right"):
            i, j = KEYPOINT_NAMES.index(f"{side}_{a}"), KEYPOINT_NAMES.index(f"{side}_{b}")
            u, v = world[:, j, :3] - world[:, i, :3], cam[:, j] - cam[:, i]
            cos = (u * v).sum(-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1) + 1e-9)
            per_side.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        angles[bone] = float(np.median(np.concatenate(per_side)))
    hips = [KEYPOINT_NAMES.index("left_hip"), KEYPOINT_NAMES.index("right_hip")]
    return {
        "case": case,
        "seed": seed,
        "angle_deg": angles,
        "hip_visibility": float(world[:, hips, 3].mean()),
    }


def run(args) -> None:
    from eva_engine.body import load_body_model
    from eva_engine.synth.hard import HARD_CASES

    torch.set_num_threads(args.threads)
    model = load_body_model("anny")
    for case in args.cases or list(HARD_CASES):
        for name in args.variants or FIT_VARIANTS:
            out = args.work / "fit_levers" / f"{case}_s{args.seed}" / name
            if not claim(out):
                continue
            result = {**run_fit(case, args.seed, name, args.work, model), "machine": describe()}
            (out / "result.json").write_text(json.dumps(result, indent=1))
            print(case, name, round(result["fit_iou"], 3), flush=True)
        world = args.work / "fit_levers" / f"{case}_s{args.seed}" / "world.json"
        if not world.is_file():
            world.write_text(json.dumps(world_landmark_errors(case, args.seed, args.work, model), indent=1))


def report(args) -> None:
    from eva_engine.synth.hard import HARD_CASES

    folder = args.work / "fit_levers"
    runs = [json.loads(p.read_text()) for p in sorted(folder.glob("*/*/result.json"))]
    worlds = [json.loads(p.read_text()) for p in sorted(folder.glob("*/world.json"))]
    base = {(r["case"], r["seed"]): r for r in runs if r["variant"] == "baseline"}
    rows = []
    for case in HARD_CASES:
        for name in FIT_VARIANTS:
            for r in (r for r in runs if r["case"] == case and r["variant"] == name):
                b = base.get((case, r["seed"]))
                gain = f"{r['fit_iou'] - b['fit_iou']:+.3f}" if b else "-"
                e, k = r["joint_error_px"], r.get("skin_error_px", {})
                rows.append(
                    f"| {case} | {name} | {r['seed']} | {r['fit_iou']:.3f} | {gain} | "
                    + " | ".join(f"{e[g]:.1f}" for g in JOINT_GROUPS)
                    + " | "
                    + " | ".join(f"{k[p]:.1f}" if p in k else "-" for p in SKIN_COLUMNS)
                    + f" | {r['fit_s']:.0f} |"
                )
    world_rows = [
        f"| {w['case']} | {w['seed']} | {w['hip_visibility']:.2f} | "
        + " | ".join(f"{w['angle_deg'][b]:.1f}" for b in ARMS)
        + " |"
        for w in worlds
    ]
    header = run_header()
    lines = [
        "# The fit against the truth on the hard clips",
        "",
        header_line(header),
        "- runs: `python bench/fit_levers.py --seed S [--variants ...]` (1 thread, beside training runs on "
        "the 2 cores: the times are inflated by that sharing)",
        f"- machine: {runs[0]['machine'] if runs else describe()}",
        f"- clips: `eva_engine.synth.hard`, {FRAMES} frames of {SIZE} px; the job path's fit "
        "(`JobOptions().preprocess_config`), one change per variant (`bench/closeup_levers.py`'s `VARIANTS`)",
        "",
        "Fit IoU: the fitted body's silhouette against the true person mask, mean over the frames (the "
        "true poses give 0.997 on the close-up); gain: against the baseline. Joint error: fitted against "
        "true keypoints in the image, px (512 px frames), mean over the frames. Skin error: fitted against "
        "true projections of each part's vertices, px, median over the part, mean over the frames; torso "
        "slide: the frame-to-frame spread of the torso's mean offset, px (the module docstring).",
        "",
        "| case | variant | seed | fit IoU | gain | "
        + " | ".join(f"{g} (px)" for g in JOINT_GROUPS)
        + " | "
        + " | ".join(f"skin: {p} (px)" for p in SKIN_COLUMNS)
        + " | fit (s) |",
        "|---|---|---:|---:|---:|" + "---:|" * (len(JOINT_GROUPS) + len(SKIN_COLUMNS)) + "---:|",
        *rows,
        "",
        "What the fit's 3D term is held to: the angle between MediaPipe's 3D world landmarks' arm bones "
        "and the true ones (median over both arms and the frames, degrees), and the hips' mean visibility "
        "(MediaPipe's world skeleton is centred on them).",
        "",
        "| case | seed | hip visibility | " + " | ".join(f"{b} (deg)" for b in ARMS) + " |",
        "|---|---:|---:|" + "---:|" * len(ARMS),
        *world_rows,
    ]
    doc = {**header, "runs": runs, "world_landmarks": worlds}
    write_result(args.out, args.name, doc, lines, show=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", nargs="+", default=None)
    ap.add_argument("--variants", nargs="+", choices=FIT_VARIANTS, default=None)
    ap.add_argument("--work", type=Path, default=ROOT / "data" / "hard_inputs")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    ap.add_argument("--name", default="fit_levers", help="the report's file stem")
    ap.add_argument("--report", action="store_true", help="gather the runs' results")
    args = ap.parse_args(argv)
    report(args) if args.report else run(args)


if __name__ == "__main__":
    main()
