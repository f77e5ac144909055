"""Alignment benchmark: MediaPipe detections -> body-model fit, measured against ground truth,
plus the real videos in ../shared/reference/videos (reprojection statistics and overlays).

    .venv/bin/python -m bench align                       # synthetic wild bench + real videos
    .venv/bin/python -m bench align --no-videos --frames 60

Synthetic part: the `wild` preset (UPB-like waist-up signer, 512 px); detections come from running
MediaPipe Holistic on the rendered frames (train + novel-pose frames, in temporal order); the
fit uses the dataset's camera. Reports MPJPE (mm; body hip-centred, hands wrist-centred) and
median 2D error (px) against the ground truth and against the detections, for the initial
estimate and after fitting, and the fitting time. Real part: `eva preprocess` on each video
(guessed camera), the reprojection statistics, and overlays of the fitted mesh written to docs/.

With --table3, also the paper's Table 3 on our data: the same avatar training driven by the
initial estimate vs by the fitted parameters, evaluated on the novel-pose frames.

Writes bench/results/align.json and align.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.machine import local_path, portable_path, run_header, write_result
from eva_engine.align import (
    FitTargets,
    PreprocessConfig,
    detect_frames,
    initial_estimate,
    mpjpe,
    preprocess_video,
    reprojection_error,
)
from eva_engine.align.clip import fit_clip
from eva_engine.align.evaluate import (
    EXPRESSION_GROUPS,
    expression_error,
    expression_error_by_group,
    head_rotation_error,
    targets_from_params,
)
from eva_engine.align.fit import fit_sequence
from eva_engine.align.reprojection import reprojection_distances
from eva_engine.align.stages import FitConfig
from eva_engine.align.targets import POSE_BODY
from eva_engine.body import BodyParams, load_body_model
from eva_engine.data import load_dataset
from eva_engine.geometry import project_points, to_camera
from eva_engine.paths import data_dir
from eva_engine.recipes import PRESETS

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DOCS = ROOT / "docs"
VIDEOS = ROOT.parent / "shared" / "reference" / "videos"


def synthetic(model, frames: int, dataset: Path | None) -> dict:
    from eva_engine.synth import generate

    if dataset is None:
        dataset = data_dir() / "synthetic" / "wild-bench-seed0"
        if not (dataset / "meta.json").exists():
            print(f"generating {dataset} ...", flush=True)
            generate("wild", "bench", 0, dataset, model=model)
    ds = load_dataset(dataset)
    order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:frames]
    images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)

    started = time.perf_counter()
    det = detect_frames(iter(images))
    detect_s = time.perf_counter() - started
    K, view = ds.K[order], ds.viewmat[order]
    targets = det.targets(K, view)
    truth = ds.gt_params.map(lambda t: t[order])
    truth_2d = FitTargets(ds.gt_keypoints[order], K, view)

    visible = ds.gt_keypoints[order][..., 2] > 0
    started = time.perf_counter()
    init = initial_estimate(model, targets)
    init_s = time.perf_counter() - started
    result = fit_clip(model, targets, ds.timestamps[order])

    def measure(params):
        return {
            "mpjpe_mm": mpjpe(model, params, truth, visible),
            "expression_mm": expression_error(model, params, truth),
            "expression_mm_by_group": expression_error_by_group(model, params, truth),
            "head_deg": head_rotation_error(model, params, truth),
            "px_vs_ground_truth": reprojection_error(model, params, truth_2d),
            "px_vs_detections": reprojection_error(model, params, targets),
            "face_mesh_px_per_frame": face_mesh_px(model, params, targets),
        }

    # The fit itself, without detection noise: the exact projections, hand depths and world pose
    # of the true keypoints (and the detected face mesh and its depths, which have no exact
    # counterpart).
    exact = targets_from_params(model, truth, K, view, ds.image_size)
    exact = dataclasses.replace(exact, face_mesh=targets.face_mesh, face_depth=targets.face_depth)
    exact_fit = fit_clip(model, exact, ds.timestamps[order], FitConfig(hand_depth_scale=1.0))  # true depths

    per_frame = {
        "detections": per_frame_hands(model, result, truth, FitConfig()),
        "exact_targets": per_frame_hands(model, exact_fit, truth, FitConfig(hand_depth_scale=1.0)),
    }

    out = {
        "dataset": portable_path(dataset),
        "frames": len(order),
        "image_size": list(ds.image_size),
        "detection_rates": det.rates(),
        "detection_px_vs_ground_truth": _detection_error(targets, truth_2d),
        "initial": measure(init),
        "fitted": measure(result.params),
        "fitted_to_exact_targets": measure(exact_fit.params),
        "ground_truth_params": measure(truth),
        "per_frame_hands": per_frame,
        "seconds": {"detect": detect_s, "initial_estimate": init_s, "fit_total": result.seconds},
        "hands": {
            "rejected": int(result.hands_rejected.sum()),
            "filled_frames": int(((result.hand_confidence > 0) & (result.hand_confidence < 1)).sum()),
        },
    }
    out["openings"] = opening_agreement(model, targets, result.params, truth, K, view)
    before = out["initial"]["px_vs_ground_truth"]["hands"]
    after = out["fitted"]["px_vs_ground_truth"]["hands"]
    out["hand_px_reduction"] = 1.0 - after / before
    return out


def opening_agreement(model, targets, fitted, truth, K, view) -> dict:
    """Mouth and eye opening (``eval.expression_fidelity``) of the detected face mesh and of the
    fitted face surface, each against the true face surface's: {stage: {measure: Agreement}}."""
    from eva_engine.align.face_mesh import load_correspondence
    from eva_engine.eval.expression_fidelity import MEASURES, agreement, fitted_landmarks, openings

    corr = load_correspondence(model)
    if corr is None or targets.face_mesh is None:
        return {}
    reg, ids = corr.regressor(model)
    f = truth.batch_size
    Ks, views = K.expand(f, 3, 3), view.expand(f, 4, 4)
    true = openings(fitted_landmarks(model, truth, reg, ids, Ks, views))
    detected = openings(targets.face_mesh, targets.face_mesh[:, :468, 2].amax(1) > 0)
    fit = openings(fitted_landmarks(model, fitted, reg, ids, Ks, views))
    return {
        stage: {m: agreement(true[m], got[m]).to_json() for m in MEASURES}
        for stage, got in (("detected", detected), ("fitted", fit))
    }


def per_frame_hands(model, fit, truth, config: FitConfig, every: int = 10, iterations: int = 200) -> dict:
    """Would a per-frame hand solver help? Every ``every``-th frame's hands stage re-run on that
    frame alone (``iterations`` L-BFGS iterations, no smoothing) from the clip's fit; hand MPJPE on
    those frames before and after. The clip's fit shares one L-BFGS step among all frames."""
    hands = next(s for s in config.stages if s.name == "hands")
    stage_config = dataclasses.replace(
        config, stages=(dataclasses.replace(hands, iterations=iterations, smooth=0.0),)
    )
    frames = list(range(0, fit.targets.num_frames, every))
    t = fit.targets
    refit = []
    for i in frames:
        one = slice(i, i + 1)
        target = FitTargets(
            t.keypoints[one],
            t.frame_K()[one],
            t.frame_viewmat()[one],
            *(None if x is None else x[one] for x in (t.hand_depth, t.pose_world, t.face_mesh)),
        )
        refit.append(fit_sequence(model, target, init=fit.params[one], config=stage_config).params)
    keys = ("hands", "hands_rotation_aligned")
    before = mpjpe(model, fit.params[frames], truth[frames])
    after = mpjpe(model, BodyParams.cat(refit), truth[frames])
    return {
        "frames": frames,
        "iterations": iterations,
        "clip_fit_mm": {k: before[k] for k in keys},
        "per_frame_mm": {k: after[k] for k in keys},
    }


def _per_frame_hands_lines(exp: dict) -> list[str]:
    first = next(iter(exp.values()))
    lines = [
        f"### Would a per-frame hand solver help? ({len(first['frames'])} frames, every "
        f"{first['frames'][1] - first['frames'][0]}th; each frame's hands stage re-run alone for "
        f"{first['iterations']} L-BFGS iterations from the clip's fit)",
        "",
        "| targets | hands (mm), clip fit | hands (mm), per frame | rotation-aligned (mm), clip fit "
        "| rotation-aligned (mm), per frame |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, r in exp.items():
        a, b = r["clip_fit_mm"], r["per_frame_mm"]
        lines.append(
            f"| {name} | {a['hands']:.1f} | {b['hands']:.1f} | {a['hands_rotation_aligned']:.1f} "
            f"| {b['hands_rotation_aligned']:.1f} |"
        )
    return lines + [
        "",
        "Rotation-aligned: each fitted hand turned about its wrist onto the truth first (the fingers' "
        "articulation without the hand's orientation).",
        "",
    ]


def table3(model, dataset: Path, preset_name: str, iterations: int | None, image_scale: float) -> dict:
    """The paper's Table 3 on our data: the same avatar training driven by the initial estimate
    ("w/o Align") and by the fitted parameters ("w/ Align"), evaluated on the novel-pose frames
    against the rendered ground truth. Detections and both parameter sets cover the main
    camera's frames (train + test_pose); the side-view frames are not used by either run."""
    import copy

    from eva_engine.eval import ImageMetrics, evaluate_avatar
    from eva_engine.train import preset, train_avatar

    ds = load_dataset(dataset)
    order = sorted(ds.splits["train"] + ds.splits["test_pose"])
    images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    targets = detect_frames(iter(images)).targets(ds.K[order], ds.viewmat[order])
    init = initial_estimate(model, targets)
    fitted = fit_clip(model, targets, ds.timestamps[order]).params
    overrides = {"image_scale": image_scale} | ({"iterations": iterations} if iterations else {})
    config = preset(preset_name, **overrides)
    metrics = ImageMetrics()
    rows = {}
    for name, params in (("w/o Align (initial estimate)", init), ("w/ Align (fitted)", fitted)):
        full = ds.gt_params.map(lambda t: t.clone())  # side-view rows: unused by training and eval
        for j, i in enumerate(order):
            for field_name, t in full.tensors().items():
                t[i] = getattr(params, field_name)[j]
        variant = copy.copy(ds)
        variant.params = full
        started = time.perf_counter()
        result = train_avatar(variant, config, body=model)
        seconds = time.perf_counter() - started
        ev = evaluate_avatar(result.avatar, variant, "test_pose", metrics=metrics, train_seconds=seconds)
        rows[name] = ev
        print(name, {k: (v.psnr, v.ssim, v.lpips_vgg) for k, v in ev.regions.items()}, flush=True)
    return {
        "dataset": portable_path(dataset),
        "preset": preset_name,
        "iterations": config.iterations,
        "image_scale": image_scale,
        "rows": {
            k: {
                "train_seconds": v.train_seconds,
                "n_gaussians": v.num_gaussians,
                **{
                    r: {"psnr": m.psnr, "ssim": m.ssim, "lpips_vgg": m.lpips_vgg, "lpips_alex": m.lpips_alex}
                    for r, m in v.regions.items()
                },
            }
            for k, v in rows.items()
        },
    }


def face_mesh_px(model, params, targets: FitTargets) -> dict[str, float] | None:
    """Per frame, the median px distance between the detected face-mesh landmarks and the fitted
    face's correspondence points; summarised as the median and 90th percentile over frames."""
    from eva_engine.align.face_mesh import load_correspondence

    corr = load_correspondence(model)
    if corr is None or targets.face_mesh is None:
        return None
    reg, landmarks = corr.regressor(model)
    with torch.no_grad():
        cam = to_camera(model.posed_points(params, reg), targets.frame_viewmat())
        uv = project_points(cam, targets.frame_K())
    det = targets.face_mesh[:, landmarks]
    per_frame = []
    for f in range(uv.shape[0]):
        ok = det[f, :, 2] > 0
        if bool(ok.any()):
            per_frame.append(float((uv[f, ok] - det[f, ok, :2]).norm(dim=-1).median()))
    if not per_frame:
        return None
    summary = {"median": float(np.median(per_frame)), "p90": float(np.percentile(per_frame, 90))}
    return {**summary, "frames": len(per_frame)}


def _detection_error(targets: FitTargets, truth: FitTargets) -> dict[str, float]:
    """Median px distance of the confident detections from the ground truth, per group."""
    from eva_engine.body import KEYPOINT_GROUPS

    d = (targets.keypoints[..., :2] - truth.keypoints[..., :2]).norm(dim=-1)
    ok = (targets.keypoints[..., 2] > 0.5) & (truth.keypoints[..., 2] > 0)
    groups = {
        "body": torch.tensor(POSE_BODY),
        "hands": torch.arange(KEYPOINT_GROUPS["left_hand"].start, KEYPOINT_GROUPS["right_hand"].stop),
        "face": torch.arange(KEYPOINT_GROUPS["face"].start, KEYPOINT_GROUPS["face"].stop),
    }
    return {k: float(d[:, i][ok[:, i]].median()) for k, i in groups.items()}


def real_videos(model, frames: int, every: int) -> list[dict]:
    rows = []
    for video in sorted(VIDEOS.glob("*.mp4")):
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "ds"
            started = time.perf_counter()
            report = preprocess_video(
                video, out, PreprocessConfig(every=every, max_frames=frames, max_size=512), model=model
            )
            total = time.perf_counter() - started
            ds = load_dataset(out)
            overlay = DOCS / f"align_overlay_{video.stem}.jpg"
            _overlay(model, ds, overlay)
            outliers = _body_outliers(model, ds)
        row = report.to_json()
        row.update(video=video.name, total_seconds=total, overlay=str(overlay.relative_to(ROOT)))
        row["body_outliers"] = outliers
        rows.append(row)
        print(json.dumps(row, indent=1), flush=True)
    return rows


def _body_outliers(model, ds, off: float = 0.2) -> dict:
    """Where the fit left a body joint far from its detection: the 90th percentile of the body
    joints' 2D error (px) and the share of frames with a confident joint (> 0.5) more than
    ``off`` person heights (2 sigma of the 2D term) from it -- what a median hides."""
    targets = FitTargets(ds.keypoints, ds.K, ds.viewmat)
    body = list(POSE_BODY)
    err = reprojection_distances(model, ds.params, targets)[:, body]
    ok = targets.keypoints[:, body, 2] > 0.5
    far = ((err / targets.person_scale()[:, None] > off) & ok).any(dim=1)
    return {"p90_px": float(err[ok].quantile(0.9)), "frames_off": float(far.float().mean())}


def _overlay(model, ds, path: Path, picks: int = 4) -> None:
    """The fitted mesh (shaded, 60% opacity) over a few frames, side by side, as a JPEG."""
    from PIL import Image

    from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer

    h, w = ds.image_size
    idx = np.linspace(0, len(ds) - 1, picks).round().astype(int).tolist()
    tiles = []
    with torch.no_grad():
        verts = model(ds.params.map(lambda t: t[idx])).vertices
    with MeshRenderer(model.faces, MeshRenderConfig(width=w, height=h, supersample=1)) as renderer:
        renderer.set_surface(
            colors=np.tile(np.array([[0.55, 0.75, 1.0]], np.float32), (model.num_vertices, 1))
        )
        for j, i in enumerate(idx):
            out = renderer.render(verts[j], ds.viewmat[i], ds.K[i])
            a = 0.6 * out.alpha[..., None]
            tiles.append(((1 - a) * ds.image(i) + a * out.rgb).clamp(0, 1))
    strip = torch.cat(tiles, dim=1).numpy()
    image = Image.fromarray((strip * 255 + 0.5).astype(np.uint8))
    image.thumbnail((1600, 400))
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, quality=85)


def markdown(report: dict) -> str:
    s = report["synthetic"]
    lines = [
        "# Alignment benchmark",
        "",
        f"- date: {report['date']}",
        f"- command: `{report['command']}`",
        f"- machine: {report['machine']}",
        "",
        f"## Synthetic `wild` preset ({s['frames']} frames, {s['image_size'][1]} px, "
        "MediaPipe on the renders)",
        "",
        "Detection rates: "
        + ", ".join(f"{k} {v:.0%}" for k, v in s["detection_rates"].items())
        + ". Detector error vs ground truth (median px): "
        + ", ".join(f"{k} {v:.1f}" for k, v in s["detection_px_vs_ground_truth"].items())
        + ".",
        "",
        "| estimate | MPJPE body in view (mm) | MPJPE body all (mm) | MPJPE hands (mm) | expression (mm) "
        "| head rotation (deg) | 2D body (px) | 2D hands (px) | 2D face (px) "
        "| face mesh px per frame (median / p90) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for name in ("initial", "fitted", "fitted_to_exact_targets", "ground_truth_params"):
        if name not in s:
            continue
        m = s[name]
        px, mp = m["px_vs_ground_truth"], m["mpjpe_mm"]
        fm = m.get("face_mesh_px_per_frame")
        fm_cell = f"{fm['median']:.2f} / {fm['p90']:.2f}" if fm else "-"
        lines.append(
            f"| {name} | {mp.get('body_in_view', float('nan')):.1f} | {mp['body']:.1f} | {mp['hands']:.1f} "
            f"| {m.get('expression_mm', float('nan')):.2f} | {m.get('head_deg', float('nan')):.1f} "
            f"| {px['body']:.2f} | {px['hands']:.2f} "
            f"| {px['face']:.2f} | {fm_cell} |"
        )
    groups = [
        n
        for n in ("initial", "fitted", "fitted_to_exact_targets")
        if "expression_mm_by_group" in s.get(n, {})
    ]
    if groups:
        lines += [
            "",
            "Expression error per facial-action group (mm; only that group's actions kept in the fit "
            "and the truth; neutral: the same for a face with no expression):",
            "",
            "| estimate | " + " | ".join(EXPRESSION_GROUPS) + " |",
            "|---|" + "---:|" * len(EXPRESSION_GROUPS),
        ]
        for name in groups:
            g = s[name]["expression_mm_by_group"]
            lines.append(f"| {name} | " + " | ".join(f"{g[k]:.2f}" for k in EXPRESSION_GROUPS) + " |")
        g = s[groups[0]]["expression_mm_by_group"]
        lines.append(
            "| neutral face | " + " | ".join(f"{g[k + '_neutral']:.2f}" for k in EXPRESSION_GROUPS) + " |"
        )
    if s.get("openings"):
        lines += [
            "",
            "Mouth and eye opening (`eva_engine.eval.expression_fidelity`: inner-lip and lid gaps over "
            "the eye-corner distance) against the true face's, per frame: Pearson r, and the 5-95 "
            "percentile range's width over the truth's:",
            "",
            "| stage | mouth r | mouth range ratio | eyes r | eyes range ratio |",
            "|---|---:|---:|---:|---:|",
        ]
        for stage, a in s["openings"].items():
            lines.append(
                f"| {stage} | {a['mouth']['r']:.2f} | {a['mouth']['range_ratio']:.2f} "
                f"| {a['eyes']['r']:.2f} | {a['eyes']['range_ratio']:.2f} |"
            )
    sec = s["seconds"]
    lines += [
        "",
        f"2D errors are medians against the ground-truth keypoints. Hand 2D error reduction by fitting: "
        f"{s['hand_px_reduction']:.0%} (goal >= 50%). Fitting {s['frames']} frames took "
        f"{sec['fit_total']:.1f} s (initial estimate {sec['initial_estimate']:.1f} s; goal <= 60 s for 150 "
        f"frames; it includes the wrong-hand check and the gap filling); detection {sec['detect']:.1f} s. "
        "MPJPE: body hip-centred (in view: only the body joints inside the image, all: every joint, "
        "legs of a waist-up frame included), hands wrist-centred; expression: mean distance of the face "
        "vertices the true expression moves, fitted vs true expression on the true rest face; head "
        "rotation: mean angle between the fitted and the true head's world rotation. "
        + (
            f"Hands: {s['hands']['rejected']} wrong-side detections dropped, {s['hands']['filled_frames']} "
            "hand-frames filled from neighbours."
            if "hands" in s
            else ""
        ),
        "",
    ]
    if s.get("per_frame_hands"):
        lines += _per_frame_hands_lines(s["per_frame_hands"])
    if report.get("table3"):
        t = report["table3"]
        lines += [
            f"## Table 3 on our data: avatar quality without / with alignment (wild preset, `{t['preset']}` "
            f"preset, {t['iterations']} iterations, image scale {t['image_scale']})",
            "",
            "| parameters | Full PSNR | Full LPIPS-VGG×1000 | Hand PSNR | Hand LPIPS-VGG×1000 | Face PSNR | "
            "Face LPIPS-VGG×1000 | N-GS |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for name, r in t["rows"].items():
            cells = []
            for region in ("full", "hand", "face"):
                m = r.get(region)
                vgg = None if m is None else m.get("lpips_vgg")  # runs before LPIPS-VGG: not measured
                lp = "-" if vgg is None else f"{1000 * vgg:.1f}"
                cells += ["-", "-"] if m is None else [f"{m['psnr']:.2f}", lp]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {r['n_gaussians']:,} |")
        lines.append("")
    if report.get("videos"):
        lines += [
            "## Real videos (`eva preprocess`, guessed camera)",
            "",
            "| video | frames kept / decoded | pose / L hand / R hand / face found "
            "| 2D px initial (body, hands, face) | 2D px fitted (body, hands, face) "
            "| fitted body: p90 px / frames with a joint > 0.2 heights off | align s | overlay |",
            "|---|---|---|---|---|---|---:|---|",
        ]
        for r in report["videos"]:
            rates = " / ".join(
                f"{r['detection_rates'][k]:.0%}" for k in ("pose", "left_hand", "right_hand", "face")
            )

            def fmt(d):
                return ", ".join("-" if d[k] is None else f"{d[k]:.1f}" for k in ("body", "hands", "face"))

            o = r.get("body_outliers")
            outliers = "-" if o is None else f"{o['p90_px']:.1f} / {o['frames_off']:.0%}"
            lines.append(
                f"| {r['video']} | {r['kept_frames']} / {r['decoded_frames']} | {rates} | "
                f"{fmt(r['reprojection_initial'])} | {fmt(r['reprojection_fitted'])} | {outliers} | "
                f"{r['seconds'].get('align', 0):.1f} | [{Path(r['overlay']).name}](../../{r['overlay']}) |"
            )
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument(
        "--dataset", type=Path, default=None, help="a wild-preset dataset (default: generate)"
    )
    parser.add_argument("--no-videos", action="store_true", help="skip the real videos")
    parser.add_argument("--video-frames", type=int, default=100)
    parser.add_argument("--video-every", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--table3", action="store_true", help="also train avatars without / with alignment")
    parser.add_argument("--table3-preset", default="fast", choices=list(PRESETS))
    parser.add_argument("--table3-iterations", type=int, default=None)
    parser.add_argument("--table3-scale", type=float, default=0.5, help="image scale for the Table 3 runs")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    model = load_body_model("anny")
    report = {
        **run_header(),
        "synthetic": synthetic(model, args.frames, args.dataset),
    }
    print(json.dumps(report["synthetic"], indent=1), flush=True)
    if args.table3:
        dataset = local_path(report["synthetic"]["dataset"])
        report["table3"] = table3(
            model, dataset, args.table3_preset, args.table3_iterations, args.table3_scale
        )
    if not args.no_videos and VIDEOS.is_dir():
        report["videos"] = real_videos(model, args.video_frames, args.video_every)
    args.out.mkdir(parents=True, exist_ok=True)
    write_result(args.out, "align", report, markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
