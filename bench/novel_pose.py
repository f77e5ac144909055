"""Novel poses and novel views: what the render endpoint is for, scored against ground truth.

The synthetic ``novel`` preset (``eva synth --preset novel``): the controlled subject, trained on
one take whose arms stay below the shoulders while the body turns +-0.5 rad, tested on four
splits: ``near`` (other takes of that generator), ``far`` (a take raising the arms above the
shoulders), ``view`` (training poses from 35 and 70 deg) and ``far_view`` (far poses from 35 deg).
Each test frame's novelty is in the dataset (``extra["novelty"]``: the largest body-joint angle
to the nearest training pose, the camera's yaw about the body).

Metrics per split: PSNR / SSIM / LPIPS-VGG (held out: nothing trains on it) on the full image,
each hand, the face and each arm (the arms' masks come from the body model's skinning, rendered
by the mesh renderer), and the silhouette errors of ``eval.debris_and_holes``: **debris**, the
share of the render's alpha outside the true person mask widened by 2 px, and **holes**, the
share of the person mask the render leaves below alpha 0.5.

Rows (``ROWS``) are the product's default training (no ``--method``) with options switched by
``--set`` overrides, so a row is the method with options on or off, never a copy; ``before`` is
main before this work (every option below off, ``OFF``) and ``thin`` is today's default. Seeds
run one process each, side by side:

    .venv/bin/python -m bench novel_pose --seeds 0 --name novel_pose_seed0 --rows before scale_cap
    .venv/bin/python -m bench novel_pose --merge novel_pose_seed0 novel_pose_seed1 novel_pose_seed2

Writes ``bench/results/<name>.json``, shaped ``{"config", "methods": {row: {"seeds", "summary",
"overrides", "splits": {near|far|view|far_view: {full|hand|face|arm: {psnr|ssim|lpips_vgg:
{mean, std}}, "debris": {mean, std}, "holes": {mean, std}}}, "n_gaussians", "train_seconds",
"runs": [per-seed entries]}}}``, and ``<name>.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, resumable, run_header, write_result
from bench.novel_pose_tables import by_novelty, view_breakdown
from bench.seed_results import merged_header, union_of_runs
from bench.stats import compare_paired, fmt, mean_std
from eva_engine.recipes import PRESETS, describe_presets
from eva_engine.synth_names import SYNTH_SIZES, describe_synth_sizes

RESULTS = Path(__file__).resolve().parent / "results"
SPLITS = {"near": "test_pose", "far": "test_far_pose", "view": "test_view", "far_view": "test_far_view"}
EVERY = {"near": 2, "far": 1, "view": 2, "far_view": 1}
"""Every k-th frame of each split is scored (LPIPS-VGG on a 512 px frame takes seconds on a core):
near 20 of its 40 frames (both takes), view 15 of 30 (both angles), all of far and far_view."""
REGIONS = ("full", "hand", "face", "arm")
METRICS = ("psnr", "ssim", "lpips_vgg")
SILHOUETTE = ("debris", "holes")
LOWER_IS_BETTER = {"psnr": False, "ssim": False, "lpips_vgg": True, "debris": True, "holes": True}


@dataclass(frozen=True)
class Row:
    """A benchmark row: the default training (or ``method``) with ``overrides`` (``--set``)."""

    summary: str
    overrides: tuple[str, ...] = ()
    method: str | None = None
    extra: dict = field(default_factory=dict)
    face_crops: bool = False
    """Trains on the dataset's face close-ups (``eva_engine.synth.face_crops``, rendered on first use)."""


DEFAULT_ROW = "thin_blink_colours"
"""The row whose options were the defaults until the presets' 0.1 px² dilation (``classic_eps01``
adds it); the rows after it are compared with it."""
OFF = (
    "regularizers.lambda_thin=0",
    "avatar.max_scale=null",
    "avatar.init_normal_ratio=1.0",
    "avatar.expression_colours=false",
    "avatar.eps2d=0.3",
)
"""Every option this benchmark tried, off: main before the work (730d452), 3DGS's 0.3 px²
dilation included, so each row trains as it did when it was measured."""
THIN = (*OFF, "regularizers.lambda_thin=0.05", "regularizers.thin_target=0.002")
"""The thin term on (the default before the blink colours)."""
DEFAULT = (
    *THIN,
    "avatar.expression_colours=true",
    'avatar.expression_colour_actions=["eyeBlinkLeft","eyeBlinkRight"]',
)
"""The overrides of ``DEFAULT_ROW``; today's defaults are these and ``avatar.eps2d=0.1``."""

ROWS: dict[str, Row] = {
    "before": Row("main before this work (730d452): every option off", OFF),
    "scale_cap": Row(
        "scales bounded per part (body 1 cm, hand and face 5 mm), initial Gaussians flat on the surface",
        (*OFF, "avatar.max_scale=[0.01,0.005,0.005]", "avatar.init_normal_ratio=0.2"),
    ),
    "thin": Row(
        "thin along the surface normal (regulariser, 2 mm): the default before the blink colours",
        THIN,
    ),
    "thin_colours": Row(
        "thin along the normal, and colours that follow the expression (issue 39)",
        (
            *THIN,
            "avatar.expression_colours=true",
        ),
    ),
    "thin_blink_colours": Row(
        "thin along the normal, and colours that follow the blinks only (issue 39): the default",
        DEFAULT,
    ),
    "median_eyes": Row(
        "the default, its Gaussians on the training frames' median face and those seen through an eye's "
        "opening attached to the eyeball (issue 39)",
        (
            *DEFAULT,
            'avatar.template_expression="median"',
            "avatar.eye_binding=true",
        ),
    ),
    "median_face": Row(
        "the default, its Gaussians on the training frames' median face (issue 39)",
        (
            *DEFAULT,
            'avatar.template_expression="median"',
        ),
    ),
    "blink_events": Row(
        "the default, each training frame with a fitted blink visited three more times per epoch (issue 39)",
        (
            *DEFAULT,
            "expression_events.repeats=3",
        ),
    ),
    "thin_face_off": Row(
        "thin along the normal except on the face's Gaussians (issue 39)",
        (
            *THIN,
            "regularizers.thin_part_weights=[1,1,0]",
        ),
    ),
    "thin_face_1cm": Row(
        "thin along the normal, the face's Gaussians free up to 1 cm instead of 2 mm (issue 39)",
        (
            *THIN,
            "regularizers.thin_part_targets=[0.002,0.002,0.01]",
        ),
    ),
    "face_closeups": Row(
        "the default, trained on the face close-ups too (256 px, about 3x the frame's pixels across the "
        "face; issue 39's option)",
        (*DEFAULT, "face_view.weight=1"),
        face_crops=True,
    ),
    "antialiased": Row(
        "the default, rasterized in gsplat's antialiased mode (issue 39)",
        (*DEFAULT, 'avatar.rasterize_mode="antialiased"'),
    ),
    "antialiased_eps01": Row(
        "the default, rasterized in gsplat's antialiased mode with Mip-Splatting's 2D filter of 0.1 px^2 "
        "(issue 39)",
        (*DEFAULT, 'avatar.rasterize_mode="antialiased"', "avatar.eps2d=0.1"),
    ),
    "classic_eps01": Row(
        "the default, its classic rasterization's 2D dilation 0.1 px^2 instead of 3DGS's 0.3 (issue 39; "
        "every preset's since)",
        (*DEFAULT, "avatar.eps2d=0.1"),
    ),
    "blink_colours_ridge": Row(
        "every preset's 0.1 px^2 dilation, and the blinks' colours under a ridge of 1e-3 (issue 39)",
        (*DEFAULT, "avatar.eps2d=0.1", "regularizers.lambda_colour_offsets=0.001"),
    ),
    "lid_colours_ridge": Row(
        "every preset's 0.1 px^2 dilation, and colours that follow all six lid actions (blinks, squints, "
        "wides) under a ridge of 1e-3 (issue 39)",
        (
            *DEFAULT,
            "avatar.eps2d=0.1",
            'avatar.expression_colour_actions=["eyeBlinkLeft","eyeBlinkRight","eyeWideLeft","eyeWideRight",'
            '"eyeSquintLeft","eyeSquintRight"]',
            "regularizers.lambda_colour_offsets=0.001",
        ),
    ),
    "face_closeups_antialiased": Row(
        "the default, trained on the face close-ups too, rasterized in gsplat's antialiased mode (issue 39)",
        (*DEFAULT, "face_view.weight=1", 'avatar.rasterize_mode="antialiased"'),
        face_crops=True,
    ),
    "face_closeups_antialiased_eps01": Row(
        "the default, trained on the face close-ups too, rasterized in gsplat's antialiased mode with "
        "Mip-Splatting's 2D filter of 0.1 px^2 (issue 39)",
        (*DEFAULT, "face_view.weight=1", 'avatar.rasterize_mode="antialiased"', "avatar.eps2d=0.1"),
        face_crops=True,
    ),
    "face_closeups_eps01": Row(
        "the default, trained on the face close-ups too, its classic rasterization's 2D dilation 0.1 px^2 "
        "(issue 39: the close-ups with every preset's dilation)",
        (*DEFAULT, "face_view.weight=1", "avatar.eps2d=0.1"),
        face_crops=True,
    ),
    "final_prune": Row(
        "a final prune: 3-sigma extent beyond 6 cm of the template, and never-seen Gaussians",
        (*OFF, "strategy.prune_extent=0.06", "strategy.prune_never_seen=true"),
    ),
    "knn_std": Row(
        "GART's KNN-std regulariser (3 neighbours, 1e-3)", (*OFF, "regularizers.lambda_knn_std=0.001")
    ),
    "skinning_prior": Row(
        "skinning weights kept near the body model's (squared distance, weight 1)",
        (*OFF, "regularizers.lambda_skinning=1.0"),
    ),
    "pose_noise": Row("pose noise in training (0.05 rad on the body joints)", (*OFF, "pose_noise=0.05")),
    "random_bg": Row("a random background colour each step", (*OFF, "random_background=true")),
    "sh0": Row("SH degree 0 (no view-dependent colour)", (*OFF, "avatar.sh_degree=0")),
    "thin_cap": Row(
        "thin along the normal and scales bounded per part (the two that won alone, together)",
        (
            *THIN,
            "avatar.max_scale=[0.01,0.005,0.005]",
            "avatar.init_normal_ratio=0.2",
        ),
    ),
}


def dataset_for(size: str, seed: int, face_crops: bool = False) -> Path:
    """The cached ``novel`` dataset of ``size`` and ``seed`` (rendered on first use); with
    ``face_crops``, with its face close-ups rendered too. Close-ups change no row that does not
    train on them (``face_view.weight`` 0), so one dataset serves every row."""
    from eva_engine.paths import data_dir
    from eva_engine.synth import generate

    path = data_dir() / "synthetic" / f"novel-{size}-seed{seed}"
    if not (path / "meta.json").is_file():
        print(f"generating {path} ...", file=sys.stderr, flush=True)
        generate("novel", size, seed, path, overwrite=True)
    if face_crops and not (path / "face_crops").is_dir():
        from eva_engine.align.face_mesh import load_correspondence
        from eva_engine.body import load_body_model
        from eva_engine.data import load_dataset
        from eva_engine.eval.expression_fidelity import fitted_landmarks
        from eva_engine.synth.face_crops import render_face_crops

        print(f"rendering the face close-ups of {path} ...", file=sys.stderr, flush=True)
        model, ds = load_body_model("anny"), load_dataset(path)
        reg, ids = load_correspondence(model).regressor(model)
        face_mesh = fitted_landmarks(model, ds.gt_params, reg, ids, ds.K, ds.viewmat)
        if render_face_crops(path, face_mesh, model=model) is None:
            raise SystemExit(f"{path}: its faces are too small for close-ups")
    return path


def arm_masks(ds, indices: list[int]) -> dict[int, dict[str, torch.Tensor]]:
    """{frame: {"arm_left", "arm_right": [H, W]}} rendered from the ground truth."""
    from eva_engine.body import load_body_model
    from eva_engine.data.region_masks import ARM_REGIONS, region_masks

    model = load_body_model("anny")
    rows = torch.tensor(indices)
    masks = region_masks(
        model, ds.gt_params[rows], ds.K[rows], ds.viewmat[rows], ds.image_size, arms=True, supersample=2
    )
    return {i: {r: torch.from_numpy(m[r]) for r in ARM_REGIONS} for i, m in zip(indices, masks, strict=True)}


def sheet_frames(ds) -> list[int]:
    """One frame per split for the contact sheet: the scored frame of most novelty (pose for
    near and far, both view angles for view)."""
    novelty = ds.meta.extra["novelty"]
    views = ds.meta.extra["view_deg_of_frame"]
    picks = []
    for split, name in SPLITS.items():
        ids = ds.splits[name][:: EVERY[split]]
        if split == "view":
            picks += [next(i for i in ids if views[i] == angle) for angle in sorted({views[i] for i in ids})]
        else:
            picks.append(max(ids, key=lambda i: novelty[str(i)]["pose_deg"]))
    return picks


def contact_sheet(ds, avatar, frames: list[int], tile: int = 192) -> np.ndarray:
    """uint8 [tile * len(frames), 2 * tile, 3]: per frame, target | render (white background)."""
    import cv2

    from eva_engine.avatar import Camera
    from eva_engine.train.losses import composite_target

    white = torch.ones(3)
    rows = []
    for i in frames:
        frame = ds[i]
        h, w = frame.image.shape[:2]
        cam = Camera(frame.K.float(), frame.viewmat.float(), w, h)
        with torch.no_grad():
            render = avatar(ds.gt_params[i], cam, white).image.clamp(0, 1)
        pair = [composite_target(frame.image, frame.mask, white), render]
        tiles = [
            cv2.resize((t.numpy() * 255 + 0.5).astype(np.uint8), (tile, tile), interpolation=cv2.INTER_AREA)
            for t in pair
        ]
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def closeup_views(ds, avatar, frames: list[int]) -> tuple[list[np.ndarray], list[torch.Tensor]]:
    """(renders uint8 [S, S, 3], targets [S, S, 3] over white) through the face close-up cameras
    of ``frames`` (each must have one): the true pose, the close-up's size."""
    from eva_engine.avatar import Camera
    from eva_engine.train.losses import composite_target

    crops, white = ds.face_crops, torch.ones(3)
    renders, targets = [], []
    with torch.no_grad():
        for i in frames:
            cam = Camera(crops.intrinsics(i, ds.K[i]), ds.viewmat[i].float(), crops.size, crops.size)
            image = avatar(ds.gt_params[i], cam, white).image.clamp(0, 1)
            renders.append((image.numpy() * 255.0 + 0.5).astype(np.uint8))
            targets.append(composite_target(crops.image(i), crops.mask(i), white))
    return renders, targets


def closeup_sheet(ds, avatar, frames: list[int], tile: int = 256) -> np.ndarray:
    """uint8 [tile * len(frames), 2 * tile, 3]: per frame, the face close-up's target | render."""
    renders, targets = closeup_views(ds, avatar, frames)
    rows = [
        np.concatenate([(t.numpy() * 255.0 + 0.5).astype(np.uint8), r], axis=1)
        for r, t in zip(renders, targets, strict=True)
    ]
    return np.concatenate(rows, axis=0)


def run_one(ds, config, metrics, arms, label: str, sheet: Path | None = None) -> dict:
    from eva_engine.eval import evaluate_avatar
    from eva_engine.train import train_avatar

    def report(e) -> None:
        if e.stage == "train" and e.done % 200 == 0:
            print(f"  [{label}] {e.message}, {e.elapsed:.0f}s", file=sys.stderr, flush=True)

    result = train_avatar(ds, config, progress=report)
    t0 = time.perf_counter()
    largest = result.avatar.gaussians.scales().detach().amax(dim=-1)
    novelty = ds.meta.extra["novelty"]
    entry: dict = {
        "n_gaussians": len(result.avatar.gaussians),
        "gaussians_per_part": result.gaussians_per_part,
        "train_seconds": result.train_seconds,
        "final_loss": result.losses[-1],
        "refinements": result.refinements,
        "scale_max_m": float(largest.max()),
        "scale_over_1cm": float((largest > 0.01).float().mean()),
        "splits": {},
    }
    for split, name in SPLITS.items():
        ev = evaluate_avatar(
            result.avatar, ds, split=name, metrics=metrics, extra_regions=arms, every=EVERY[split]
        )
        out: dict = {}
        for region, m in ev.regions.items():
            out[region] = {k: getattr(m, k) for k in (*METRICS, "lpips_alex", "frames", "crops", "box_px")}
        out["debris"], out["holes"] = ev.regions["full"].debris, ev.regions["full"].holes
        out["per_frame"] = {
            str(i): {
                **{k: rows["full"][k] for k in ("psnr", "lpips_vgg", "debris", "holes")},
                **{f"{r}_lpips_vgg": rows[r]["lpips_vgg"] for r in ("hand", "face", "arm") if r in rows},
                **novelty[str(i)],
                "view_deg": ds.meta.extra["view_deg_of_frame"][i],
            }
            for i, rows in ev.per_frame.items()
        }
        ids = [i for i in ds.splits[name][:: EVERY[split]] if ds.face_crops and ds.face_crops.has(i)]
        if ids:  # the head at about 3x the frame's pixels, from the split's cameras
            from bench.expressions import closeup_scores

            scores = closeup_scores(*closeup_views(ds, result.avatar, ids), lpips=metrics.lpips_vgg)
            out["closeup"] = {k: scores[k] for k in ("frames", "psnr", "lpips_vgg")}
            for i, value in zip(ids, scores["per_frame"]["lpips_vgg"], strict=True):
                out["per_frame"][str(i)]["closeup_lpips_vgg"] = value
        entry["splits"][split] = out
    entry["eval_seconds"] = time.perf_counter() - t0
    if sheet is not None:
        from PIL import Image

        picks = sheet_frames(ds)
        sheet.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(contact_sheet(ds, result.avatar, picks)).save(sheet, quality=85, optimize=True)
        entry["contact_sheet"] = {"file": sheet.name, "frames": picks}
        if ds.face_crops is not None:
            faces = sheet.with_name(f"{sheet.stem}_face.jpg")
            picks = [i for i in picks if ds.face_crops.has(i)]
            Image.fromarray(closeup_sheet(ds, result.avatar, picks)).save(faces, quality=90, optimize=True)
            entry["closeup_sheet"] = {"file": faces.name, "frames": picks}
    s = entry["splits"]
    print(
        f"  [{label}] {entry['n_gaussians']} GS, {entry['train_seconds']:.0f}s; "
        + "; ".join(
            f"{k} LPIPS-VGG {1000 * v['full']['lpips_vgg']:.1f} debris {100 * v['debris']:.2f}%"
            for k, v in s.items()
        ),
        file=sys.stderr,
        flush=True,
    )
    return entry


def aggregate(row: Row, runs: list[dict]) -> dict:
    """A row's summary over its per-seed runs (the result file's shape)."""
    out: dict = {
        "summary": row.summary,
        "method": row.method,
        "overrides": list(row.overrides),
        "seeds": [r["seed"] for r in runs],
        "n_gaussians": mean_std([r["n_gaussians"] for r in runs]),
        "train_seconds": mean_std([r["train_seconds"] for r in runs]),
        "splits": {},
    }
    for split in SPLITS:
        per = [r["splits"][split] for r in runs]
        agg: dict = {}
        for region in REGIONS:
            if all(region in p for p in per):
                agg[region] = {m: mean_std([p[region][m] for p in per]) for m in METRICS}
        if all("closeup" in p for p in per):
            agg["closeup"] = {m: mean_std([p["closeup"][m] for p in per]) for m in ("psnr", "lpips_vgg")}
        for key in SILHOUETTE:
            agg[key] = mean_std([p[key] for p in per])
        out["splits"][split] = agg
    out["runs"] = runs
    return out


def paired(a_runs: list[dict], b_runs: list[dict], split: str) -> tuple[list[int], list[str]]:
    """Row a against row b on one split, paired over the seeds both ran: LPIPS-VGG and PSNR per
    region, debris and holes (``stats.compare_paired``)."""
    a = {r["seed"]: r["splits"][split] for r in a_runs}
    b = {r["seed"]: r["splits"][split] for r in b_runs}
    seeds = sorted(a.keys() & b.keys())
    cells = []
    for region in (*REGIONS, "closeup"):
        if any(region not in a[s] or region not in b[s] for s in seeds):
            continue
        for metric, label in (("lpips_vgg", "LPIPS-VGG"), ("psnr", "PSNR")):
            cells.append(
                (
                    f"{region} {label}",
                    [a[s][region][metric] for s in seeds],
                    [b[s][region][metric] for s in seeds],
                )
            )
    for key in SILHOUETTE:
        cells.append((key, [a[s][key] for s in seeds], [b[s][key] for s in seeds]))
    out = []
    for label, xa, xb in cells:
        metric = label.split()[-1].lower().replace("-", "_")
        verdict, gap = compare_paired(xa, xb, LOWER_IS_BETTER.get(metric, True))
        if verdict == "too few seeds":
            out.append(f"{label} {gap['mean']:+.1f}% (one seed)")
        else:
            out.append(f"{label} {verdict} ({gap['mean']:+.1f} ± {gap['std']:.1f}%)")
    return seeds, out


def markdown(doc: dict) -> str:
    cfg = doc["config"]
    methods = doc["methods"]
    lines = [
        "# Novel poses and novel views",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- data: `eva synth --preset novel --size {cfg['size']} --seed s` for s in {cfg['seeds']} "
        f"({cfg['image_size'][1]}x{cfg['image_size'][0]} px; train on {cfg['train_frames']} frames of one "
        "take, arms below the shoulders, body turning +-0.5 rad; ground-truth body parameters)",
        f"- test frames per split: {cfg['test_frames']}",
        f"- training: preset `{cfg['preset']}`, training seed = data seed, {cfg['threads']} thread(s) per "
        f"process; compute time {doc['total_seconds'] / 3600:.1f} h",
        "",
        "Every cell is the mean ± std over the seeds. LPIPS ×1000, VGG (held out: nothing trains on "
        "it). Debris: the share of the render's alpha outside the true person mask widened by 2 px; "
        "holes: the share of the person mask the render leaves below alpha 0.5 (both in %). Hand, "
        "face and arm: each on its own crop (`docs/evaluation.md`).",
        "",
        "## Novelty of the test splits",
        "",
        "| split | frames | pose: largest joint angle to the nearest training pose (deg), median [min, max] "
        "| camera yaw about the body (deg), [min, max] |",
        "|---|---:|---|---|",
    ]
    first = next(iter(methods.values()))["runs"]
    for split in SPLITS:
        frames = [f for r in first for f in r["splits"][split]["per_frame"].values()]
        pose = sorted(f["pose_deg"] for f in frames)
        yaw = [f["yaw_deg"] for f in frames]
        lines.append(
            f"| {split} | {len(frames) // max(len(first), 1)} | {statistics.median(pose):.0f} "
            f"[{pose[0]:.0f}, {pose[-1]:.0f}] | [{min(yaw):.0f}, {max(yaw):.0f}] |"
        )
    train_yaw = cfg.get("train_yaw_deg")
    if train_yaw:
        lines += [
            "",
            f"Training frames: camera yaw about the body {train_yaw[0]:.0f} to {train_yaw[1]:.0f} deg.",
        ]
    lines.append("")
    for split in SPLITS:
        lines += [
            f"## {split}",
            "",
            "| row | N-GS | Full PSNR↑ | Full LPIPS-VGG↓ | Hand LPIPS-VGG↓ | Face LPIPS-VGG↓ "
            "| Arm LPIPS-VGG↓ | Debris %↓ | Holes %↓ |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for name, e in methods.items():
            s = e["splits"][split]
            cells = [name, fmt(e["n_gaussians"], digits=0), fmt(s["full"]["psnr"])]
            cells += [fmt(s[r]["lpips_vgg"], 1000, 1) if r in s else "–" for r in REGIONS]
            cells += [fmt(s["debris"], 100, 2), fmt(s["holes"], 100, 2)]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["## The view split by camera angle (mean over frames, then seeds)", ""]
    lines += [
        "| row | 35°: LPIPS-VGG | 35°: debris % | 70°: LPIPS-VGG | 70°: debris % |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, e in methods.items():
        b = view_breakdown(e["runs"])
        cells = [name]
        for angle in (35, 70):
            d = b.get(angle)
            cells += [f"{1000 * d['lpips_vgg']:.1f}", f"{100 * d['debris']:.2f}"] if d else ["–", "–"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += closeup_tables(methods)
    train_yaw = {int(k): v for k, v in cfg.get("train_yaw_deg_by_seed", {}).items()}
    if train_yaw:
        ranges = ", ".join(f"seed {k}: {v[0]:.0f} to {v[1]:.0f}" for k, v in sorted(train_yaw.items()))
        lines += [
            "",
            "## Quality against novelty (every scored frame of every seed)",
            "",
            "Full-image LPIPS-VGG ×1000 and debris % by how far the camera's yaw lies beyond the training "
            f"frames' range (deg; {ranges}; negative: inside it), and for "
            "the training camera's frames (near, far) by the largest joint angle to the nearest training "
            "pose. The coverage warnings' margins (`eva_engine.avatar.coverage.CoverageMargins`) are read "
            "off these.",
            "",
        ]
        for kind, header in (("yaw_beyond", "yaw beyond the range (deg)"), ("pose", "pose distance (deg)")):
            lines += [f"| row | {header} | frames | LPIPS-VGG | debris % |", "|---|---|---:|---:|---:|"]
            for name in ("before", DEFAULT_ROW):
                for b in by_novelty(methods[name]["runs"], train_yaw)[kind] if name in methods else []:
                    lines.append(
                        f"| {name} | [{b['bin'][0]:.0f}, {b['bin'][1]:.0f}) | {b['frames']} | "
                        f"{1000 * b['lpips_vgg']:.1f} | {100 * b['debris']:.2f} |"
                    )
            lines.append("")
    baseline = doc.get("baseline", "before")
    lines += [
        f"## Against `{baseline}`",
        "",
        "Paired over the seeds both rows ran: the mean ± std over seeds of the per-seed relative gap; "
        "better / worse only when the mean exceeds the std (`bench/stats.py`), else no difference.",
        "",
    ]
    base = methods.get(baseline)
    for name, e in methods.items():
        if base is None or name == baseline:
            continue
        lines.append(f"### {name}: {e['summary']}")
        lines.append("")
        own = " ".join(o for o in e["overrides"] if o not in base["overrides"])
        lines.append(
            f"- overrides (after `{baseline}`'s): `{own or '(none)'}`"
            + (f"; method `{e['method']}`" if e["method"] else "")
        )
        for split in SPLITS:
            seeds, cells = paired(e["runs"], base["runs"], split)
            lines.append(f"- **{split}** (seeds {seeds}): " + "; ".join(cells))
        lines.append("")
    return "\n".join(lines) + "\n"


def closeup_tables(methods: dict) -> list[str]:
    """Markdown lines: the face close-ups' scores per split, and the view split's face by angle, for
    the rows scored on close-ups (none: no lines)."""
    scored = {n: e for n, e in methods.items() if all("closeup" in e["splits"][s] for s in SPLITS)}
    if not scored:
        return []
    lines = [
        "",
        "## The face close-ups (256 px, about 3x the frame's pixels across the face)",
        "",
        "The head of every scored frame through its close-up's camera (`eva_engine.synth.face_crops`), "
        "rendered in the true pose against the rendered truth: LPIPS-VGG ×1000 and PSNR. A row that "
        "trains on the close-ups sees only the training frames' (the front, 0°).",
        "",
        "| row | " + " | ".join(f"{s}: LPIPS-VGG | {s}: PSNR" for s in SPLITS) + " |",
        "|---|" + "---:|---:|" * len(SPLITS),
    ]
    for name, e in scored.items():
        cells = [name]
        for split in SPLITS:
            c = e["splits"][split]["closeup"]
            cells += [fmt(c["lpips_vgg"], 1000, 1), fmt(c["psnr"])]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "The view split's head by camera angle (mean over frames, then seeds; LPIPS-VGG ×1000):",
        "",
        "| row | 35°: face | 35°: close-up | 70°: face | 70°: close-up |",
        "|---|---:|---:|---:|---:|",
    ]
    keys = ("face_lpips_vgg", "closeup_lpips_vgg")
    for name, e in scored.items():
        b = view_breakdown(e["runs"], keys)
        cells = [name]
        for angle in (35, 70):
            d = b.get(angle)
            cells += [f"{1000 * d[k]:.1f}" for k in keys] if d else ["–"] * 2
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def merge(docs: list[dict]) -> dict:
    """One document from several (one process per seed): the union of their runs per row."""
    runs = union_of_runs(docs)
    rows: dict[str, dict] = {}
    for doc in docs:
        for name, entry in doc["methods"].items():
            rows.setdefault(name, entry)
    seeds = sorted({s for by in runs.values() for s in by})
    return {
        **merged_header(docs),
        "config": {
            **docs[0]["config"],
            "seeds": seeds,
            "train_yaw_deg_by_seed": {
                str(s): y
                for d in docs
                for s, y in (
                    d["config"].get("train_yaw_deg_by_seed")
                    or {str(d["config"]["seeds"][-1]): d["config"]["train_yaw_deg"]}
                ).items()
            },
        },
        "methods": {
            name: aggregate(
                ROWS.get(name)
                or Row(rows[name]["summary"], tuple(rows[name]["overrides"]), rows[name]["method"]),
                [by[s] for s in sorted(by)],
            )
            for name, by in runs.items()
        },
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="bench", choices=list(SYNTH_SIZES), help=describe_synth_sizes())
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--preset", default="fast", choices=list(PRESETS), help=describe_presets())
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--name", default="novel_pose", help="result file stem (.json, .md)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--sheet-seeds",
        nargs="*",
        type=int,
        default=[0],
        help="seeds whose runs save a contact sheet (target | render, one frame per split) to "
        "<out>/novel_pose/<row>_seed<s>.jpg",
    )
    ap.add_argument(
        "--sheets-only",
        action="store_true",
        help="only train the rows and write their contact sheets (no scoring, no result file)",
    )
    ap.add_argument("--merge", nargs="+", metavar="NAME", help="only combine the runs of result files")
    ap.add_argument("--replot", action="store_true", help="only rewrite the .md from the .json")
    ap.add_argument(
        "--baseline",
        choices=list(ROWS),
        help="the row the others are paired against (default: `before`; kept in the result file)",
    )
    ap.add_argument(
        "--face-crops",
        action="store_true",
        help="score every row on the face close-ups too (rendered into the datasets on first use; "
        "on whenever a row trains on them)",
    )
    ap.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = ap.parse_args(argv)
    path = args.out / f"{args.name}.json"
    if args.replot or args.merge:
        doc = (
            merge([json.loads((args.out / f"{n}.json").read_text()) for n in args.merge])
            if args.merge
            else json.loads(path.read_text())
        )
        if args.baseline:
            doc["baseline"] = args.baseline
        write_result(args.out, args.name, doc, markdown(doc), show=True)
        return

    from eva_engine.avatar.coverage import rest_root, view_angles
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset
    from eva_engine.eval import ImageMetrics
    from eva_engine.train import preset, with_method, with_overrides

    torch.set_num_threads(args.threads)
    face_crops = args.face_crops or any(ROWS[n].face_crops for n in args.rows)
    if args.sheets_only:
        from PIL import Image

        from eva_engine.train import train_avatar

        for seed in args.seeds:
            ds = load_dataset(dataset_for(args.size, seed, face_crops))
            for name in args.rows:
                row = ROWS[name]
                cfg = preset(args.preset, seed=seed)
                cfg = with_overrides(with_method(cfg, row.method) if row.method else cfg, list(row.overrides))
                avatar = train_avatar(ds, cfg).avatar
                sheet = args.out / "novel_pose" / f"{name}_seed{seed}.jpg"
                sheet.parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(contact_sheet(ds, avatar, sheet_frames(ds))).save(
                    sheet, quality=85, optimize=True
                )
                print(f"wrote {sheet}", file=sys.stderr, flush=True)
        return
    doc = resumable(json.loads(path.read_text()) if path.is_file() else {}, path)
    runs: dict[str, list[dict]] = {n: list(e["runs"]) for n, e in doc.get("methods", {}).items()}
    started, previous = time.perf_counter(), doc.get("total_seconds", 0.0)
    metrics = ImageMetrics()
    config: dict = {"size": args.size, "preset": args.preset, "threads": args.threads, "seeds": args.seeds}
    for seed in args.seeds:
        ds = load_dataset(dataset_for(args.size, seed, face_crops))
        test_ids = [i for split, name in SPLITS.items() for i in ds.splits[name][:: EVERY[split]]]
        train = torch.tensor(ds.splits["train"])
        gt = ds.gt_params[train]
        yaw, _ = view_angles(gt, ds.viewmat[train], rest_root(load_body_model("anny"), gt.shape[:1]))
        config.update(
            image_size=list(ds.image_size),
            train_frames=len(ds.splits["train"]),
            test_frames={k: len(ds.splits[v][:: EVERY[k]]) for k, v in SPLITS.items()},
            train_yaw_deg=[float(yaw.min()), float(yaw.max())],
        )
        config.setdefault("train_yaw_deg_by_seed", {})[str(seed)] = config["train_yaw_deg"]
        arms = arm_masks(ds, test_ids)
        for name in args.rows:
            if any(r["seed"] == seed for r in runs.get(name, [])):
                continue
            row = ROWS[name]
            label = f"{name} seed {seed}"
            print(f"{label} ...", file=sys.stderr, flush=True)
            cfg = preset(args.preset, seed=seed)
            cfg = with_method(cfg, row.method) if row.method else cfg
            cfg = with_overrides(cfg, list(row.overrides))
            sheet = args.out / "novel_pose" / f"{name}_seed{seed}.jpg" if seed in args.sheet_seeds else None
            entry = {
                "seed": seed,
                "train_config": cfg.to_dict(),
                **run_one(ds, cfg, metrics, arms, label, sheet),
            }
            runs.setdefault(name, []).append(entry)
            doc = {
                **run_header(),
                "load_average": [round(x, 2) for x in os.getloadavg()],
                "total_seconds": previous + time.perf_counter() - started,
                **({"baseline": args.baseline} if args.baseline else {}),
                "config": config,
                "methods": {
                    n: aggregate(
                        ROWS[n] if n in ROWS else Row(doc["methods"][n]["summary"]),
                        sorted(r, key=lambda x: x["seed"]),
                    )
                    for n, r in runs.items()
                },
            }
            args.out.mkdir(parents=True, exist_ok=True)
            write_result(args.out, args.name, doc, markdown(doc))
    print(markdown(doc) if doc else "nothing to run")


if __name__ == "__main__":
    main()
