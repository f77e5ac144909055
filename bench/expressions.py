"""Expression fidelity (issue 39): how much of the video's mouth and eye opening survives each
stage of the product, per video, with a contact sheet of face close-ups.

    V=data/real_videos_hands/latentsync_demo3_gesturing
    .venv/bin/python -m bench expressions --case gesturing $V/dataset $V/avatar-eva-<tag> --name expressions

Per case (a preprocessed dataset and an avatar trained on it): over the test frames
(``--split``), MediaPipe Holistic's face mesh on single images (no tracking) of the target
frame and of the avatar's render of it (on the background it trained on), and the measures of
``eva_engine.eval.expression_fidelity`` (mouth and eye opening over the eye-corner distance)
for each stage: ``detected`` (the landmarks preprocessing stored), ``fitted`` (the fitted face
surface projected), ``render``; each against the target: Pearson r, and the 5-95 percentile
range. With ground truth (a synthetic dataset), also ``truth`` (the true face projected) and the
fitted expression's error in mm per action group against the truth and against a neutral face
(``align.evaluate.expression_error_by_group``). ``--avatar -``: no render stage. ``--blur S``:
also the stage ``blurred``, the target itself under a Gaussian blur of S px through the same
detector: a control for how much of the render's loss a blurrier image alone would cost.
``--closeup``: the targets are the dataset's face close-ups at the video's resolution
(``eva_engine.data.face_crops``) and the renders the avatar's through their cameras, on the test
frames that have one; the measures are ratios, so the stored landmarks' stages stay comparable.
It also scores the close-ups as images (PSNR and LPIPS-VGG against the target over the trained
background, where the person mask puts it).

Writes ``bench/results/<name>.{json,md}`` and ``<name>_<case>.jpg``: face close-ups, target |
render, of the frames with the widest-open mouth and the most closed eyes in the target.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, run_header, write_result
from bench.stats import fmt, mean_std

RESULTS = Path(__file__).resolve().parent / "results"
STAGES = ("detected", "fitted", "refitted", "truth", "blurred", "render")


def detect_faces(images: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """([F, 478, 3] face-mesh landmarks, [F] found) of RGB uint8 images, each on its own."""
    from eva_engine.align.detect import DetectorConfig, HolisticDetector

    marks, found = [], []
    with HolisticDetector(DetectorConfig(video=False, segmentation=False)) as det:
        for img in images:
            d = det(img)
            marks.append(torch.from_numpy(d.face_mesh.copy()))
            found.append(bool(d.found.get("face", False)))
    return torch.stack(marks), torch.tensor(found)


def to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.clamp(0, 1).numpy() * 255).round().astype(np.uint8)


def stored_targets(ds):
    """The ``FitTargets`` of the detections a dataset stored (its keypoints, hand and face-mesh
    depths, world pose, person masks)."""
    from eva_engine.align import FitTargets

    x = ds.keypoint_extras
    return FitTargets(
        ds.keypoints,
        ds.K,
        ds.viewmat,
        hand_depth=x.get("hand_depth"),
        pose_world=x.get("pose_world"),
        face_mesh=x.get("face_mesh"),
        person_masks=ds.masks(),
        face_depth=x.get("face_depth"),
    )


def refit(model, ds):
    """The clip fitted again by this checkout's ``fit_clip`` from the detections the dataset stored
    (``stored_targets``): ``BodyParams`` [F]."""
    from eva_engine.align.clip import fit_clip

    return fit_clip(model, stored_targets(ds), ds.timestamps).params


def run_case(
    label: str,
    dataset: Path,
    avatar_dir: Path | None,
    split: str,
    every: int,
    refitting: bool = False,
    blur: float = 0.0,
    closeup: bool = False,
) -> tuple[dict, dict]:
    """(result entry, images for the sheet) of one case; ``refitting``: also the stage
    ``refitted`` (:func:`refit`); ``blur`` > 0: also the stage ``blurred`` (the module docstring)."""
    from eva_engine.align.evaluate import expression_error_by_group
    from eva_engine.align.face_mesh import load_correspondence
    from eva_engine.avatar import Camera, load_saved_avatar
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset
    from eva_engine.eval.expression_fidelity import MEASURES, agreement, fitted_landmarks, openings

    ds = load_dataset(dataset)
    indices = list(ds.splits[split])[::every]
    crops = ds.face_crops
    if closeup:
        if crops is None:
            raise SystemExit(f"{dataset} has no face close-ups (eva_engine.data.face_crops)")
        indices = [i for i in indices if crops.has(i)]
    if not indices:
        raise SystemExit(f"{dataset} has no frames in split {split!r}")
    if ds.params is None:
        raise SystemExit(f"{dataset} has no fitted parameters")
    print(f"{label}: {len(indices)} frames ...", file=sys.stderr, flush=True)
    frames = [ds[i] for i in indices]
    targets = [to_uint8(crops.image(i) if closeup else f.image) for i, f in zip(indices, frames, strict=True)]
    target_marks, target_found = detect_faces(targets)
    marks: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    stored = ds.keypoint_extras.get("face_mesh")
    if stored is not None:
        s = stored[indices]
        marks["detected"] = (s, s[:, :468, 2].amax(dim=1) > 0)

    saved = load_saved_avatar(avatar_dir) if avatar_dir is not None else None
    model = saved.avatar.body if saved is not None else load_body_model(ds.meta.body_model or "anny")
    corr = load_correspondence(model)
    if corr is None:
        raise SystemExit(f"no face-mesh correspondence for body model {model.name!r}")
    reg, ids = corr.regressor(model)
    K, view = ds.K[indices], ds.viewmat[indices]
    ones = torch.ones(len(indices), dtype=torch.bool)
    marks["fitted"] = (fitted_landmarks(model, ds.params[indices], reg, ids, K, view), ones)
    if refitting:
        print(f"{label}: fitting the clip again ...", file=sys.stderr, flush=True)
        again = refit(model, ds)
        marks["refitted"] = (fitted_landmarks(model, again[indices], reg, ids, K, view), ones)
    if ds.gt_params is not None:
        marks["truth"] = (fitted_landmarks(model, ds.gt_params[indices], reg, ids, K, view), ones)

    if blur > 0:
        import cv2

        marks["blurred"] = detect_faces([cv2.GaussianBlur(t, (0, 0), blur) for t in targets])

    renders, composited = [], []
    if saved is not None:
        cfg_bg = (saved.meta.train_config or {}).get("background")
        bg = ds.meta.background if cfg_bg is None else cfg_bg
        background = torch.tensor(bg if bg is not None else (1.0, 1.0, 1.0), dtype=torch.float32)
        saved.avatar.eval()
        with torch.no_grad():
            for i, f in zip(indices, frames, strict=True):
                h, w = f.image.shape[:2]
                cam = Camera(f.K.float(), f.viewmat.float(), w, h)
                if closeup:
                    cam = Camera(crops.intrinsics(i, f.K), f.viewmat.float(), crops.size, crops.size)
                    m = crops.mask(i)[..., None]
                    composited.append(crops.image(i) * m + background * (1 - m))
                renders.append(to_uint8(saved.avatar(ds.params[i], cam, background).image))
        marks["render"] = detect_faces(renders)

    target = openings(target_marks, target_found)
    entry: dict = {
        "dataset": str(dataset),
        "avatar": str(avatar_dir) if avatar_dir is not None else None,
        "split": split,
        "blur_px": blur,
        "frames": len(indices),
        "target_found": int(target_found.sum()),
        "stages": {},
    }
    got = {stage: openings(*marks[stage]) for stage in STAGES if stage in marks}
    for stage, measured in got.items():
        entry["stages"][stage] = {
            "found": int(marks[stage][1].sum()),
            **{m: agreement(target[m], measured[m]).to_json() for m in MEASURES},
        }
    entry["per_frame"] = {
        "index": indices,
        "target": {m: target[m].tolist() for m in MEASURES},
        **{stage: {m: measured[m].tolist() for m in MEASURES} for stage, measured in got.items()},
    }
    if composited:
        entry["closeup_images"] = closeup_scores(renders, composited)
    if ds.gt_params is not None:
        entry["expression_mm"] = expression_error_by_group(model, ds.params[indices], ds.gt_params[indices])
    images = {"targets": targets, "renders": renders, "target_marks": target_marks, "target": target}
    return entry, images


def closeup_scores(renders: list[np.ndarray], targets: list[torch.Tensor], lpips=None) -> dict:
    """Mean PSNR and LPIPS-VGG of the close-up renders (uint8 [S, S, 3]) against their targets
    ([S, S, 3] in [0, 1], over the background), and each frame's (``per_frame``: {"psnr",
    "lpips_vgg": [F]}). lpips: a ``metrics.LPIPS("vgg")`` to reuse (made if None)."""
    from eva_engine.metrics import LPIPS, psnr

    lpips = lpips or LPIPS("vgg")
    p, lp = [], []
    with torch.no_grad():
        for ren, tgt in zip(renders, targets, strict=True):
            r = torch.from_numpy(ren).float().div(255.0).permute(2, 0, 1)[None]
            t = tgt.float().clamp(0, 1).permute(2, 0, 1)[None]
            p.append(float(psnr(r, t)))
            lp.append(float(lpips(r, t).mean()))
    return {
        "frames": len(renders),
        "psnr": float(np.mean(p)),
        "lpips_vgg": float(np.mean(lp)),
        "per_frame": {"psnr": p, "lpips_vgg": lp},
    }


def face_box(marks: torch.Tensor, shape: tuple[int, int], pad: float = 0.35) -> tuple[int, int, int]:
    """(x0, y0, side) of a square around the landmarks, padded by ``pad`` of its side."""
    xy = marks[:468, :2]
    lo, hi = xy.min(0).values, xy.max(0).values
    side = int(float((hi - lo).max()) * (1 + 2 * pad)) or 64
    cx, cy = (lo + hi) / 2
    h, w = shape
    side = min(side, h, w)
    x0 = int(np.clip(float(cx) - side / 2, 0, w - side))
    y0 = int(np.clip(float(cy) - side / 2, 0, h - side))
    return x0, y0, side


def contact_sheet(images: dict, picks: list[tuple[str, int]], tile: int = 224) -> np.ndarray | None:
    """Rows of [target face | render face] for the picked frames (position in the case's list)."""
    import cv2

    if not images["renders"]:
        return None
    rows = []
    for what, k in picks:
        img, ren = images["targets"][k], images["renders"][k]
        x0, y0, side = face_box(images["target_marks"][k], img.shape[:2])
        crops = [
            cv2.resize(a[y0 : y0 + side, x0 : x0 + side], (tile, tile), interpolation=cv2.INTER_AREA)
            for a in (img, ren)
        ]
        row = np.concatenate(crops, axis=1)
        cv2.putText(row, what, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 0, 0), 1, cv2.LINE_AA)
        rows.append(row)
    return np.concatenate(rows, axis=0)


def picks_of(target: dict, n: int = 3) -> list[tuple[str, int]]:
    """The ``n`` frames of widest mouth and of most closed eyes in the target (positions)."""
    out = []
    for measure, largest, what in (("mouth", True, "mouth open"), ("eyes", False, "eyes closing")):
        x = target[measure].clone()
        x[~torch.isfinite(x)] = -math.inf if largest else math.inf
        order = torch.argsort(x, descending=largest).tolist()
        out += [
            (f"{what} {float(target[measure][k]):.3f}", k) for k in order[:n] if math.isfinite(float(x[k]))
        ]
    return out


def fmt_agreement(a: dict) -> str:
    if a["frames"] < 3:
        return "–"
    full = a.get("full_range_ratio", math.nan)
    return (
        f"{a['r']:.2f} | {a['stage_range'][0]:.3f}–{a['stage_range'][1]:.3f} | {a['range_ratio']:.2f} | "
        f"{full:.2f}"
    )


def seed_groups(labels) -> dict[str, list[str]]:
    """{group: [labels]} of the case labels ``<group>_s<seed>`` with more than one seed."""
    groups: dict[str, list[str]] = {}
    for label in labels:
        head, sep, seed = label.rpartition("_s")
        if sep and seed.isdigit():
            groups.setdefault(head, []).append(label)
    return {g: ls for g, ls in groups.items() if len(ls) > 1}


def seed_summary(doc: dict) -> list[str]:
    """Markdown lines: per group of seeds (``seed_groups``), measure and stage, mean ± std of r
    and of the range ratios (5-95 and full) over the seeds."""
    groups = seed_groups(doc["cases"])
    if not groups:
        return []
    lines = [
        "",
        "## Over seeds",
        "",
        "Mean ± std over the cases `<video>_s<seed>` (one avatar per training seed; the detected and "
        "fitted stages do not depend on the seed).",
        "",
        "| video | seeds | measure | stage | r | range ratio | full range ratio |",
        "|---|---:|---|---|---:|---:|---:|",
    ]
    for group, labels in groups.items():
        cases = [doc["cases"][label] for label in labels]
        for measure in ("mouth", "eyes"):
            for stage in cases[0]["stages"]:
                got = [c["stages"][stage][measure] for c in cases if stage in c["stages"]]
                got = [a for a in got if a["frames"] >= 3]
                if not got:
                    continue
                r = fmt(mean_std([a["r"] for a in got]))
                ratio = fmt(mean_std([a["range_ratio"] for a in got]))
                full = fmt(mean_std([a.get("full_range_ratio", math.nan) for a in got]))
                lines.append(f"| {group} | {len(got)} | {measure} | {stage} | {r} | {ratio} | {full} |")
    return lines


def markdown(doc: dict) -> str:
    lines = [
        "# Expression fidelity: mouth and eye opening, stage by stage",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        "",
        "Mouth: inner-lip gap (landmarks 13-14); eyes: mean lid gap (159-145, 386-374); both over "
        "the outer eye-corner distance (33-263). Target: MediaPipe Holistic's face mesh on each test "
        "frame (single images). Each stage against the target: Pearson r | the stage's 5-95 "
        "percentile range | that range's width over the target's | the full range's (max - min) "
        "width over the target's (a blink's few closed frames are in it, not in the 5-95 one).",
        "",
    ]
    blurs = sorted({e.get("blur_px", 0.0) for e in doc["cases"].values()} - {0.0})
    if blurs:
        lines += [
            f"Stage `blurred`: the target under a Gaussian blur of {', '.join(f'{b:g}' for b in blurs)} "
            "px, the same detector (a control: what a blurrier image alone costs the measures).",
            "",
        ]
    lines += [
        "| case | frames (face found) | measure | target range | stage | r | stage range | range ratio "
        "| full range ratio |",
        "|---|---|---|---|---|---:|---|---:|---:|",
    ]
    for label, e in doc["cases"].items():
        for measure in ("mouth", "eyes"):
            for stage, s in e["stages"].items():
                a = s[measure]
                tr = a["target_range"]
                cells = fmt_agreement(a).split(" | ") if a["frames"] >= 3 else ["–"] * 4
                lines.append(
                    f"| {label} | {e['frames']} ({e['target_found']}) | {measure} | "
                    f"{tr[0]:.3f}–{tr[1]:.3f} | {stage} ({s['found']}) | " + " | ".join(cells) + " |"
                )
    mm = {label: e["expression_mm"] for label, e in doc["cases"].items() if "expression_mm" in e}
    if mm:
        lines += [
            "",
            "## Fitted expression against the ground truth (mm, per action group)",
            "",
            "Mean distance of the face vertices each group's true actions move, fitted against true, "
            "with only that group's actions kept; 'neutral': the same for a face with no expression.",
            "",
            "| case | " + " | ".join(f"{g} | {g} neutral" for g in ("jaw", "lips", "lids", "brows")) + " |",
            "|---|" + "---:|" * 8,
        ]
        for label, e in mm.items():
            cells = [
                f"{e.get(g, float('nan')):.2f} | {e.get(g + '_neutral', float('nan')):.2f}"
                for g in ("jaw", "lips", "lids", "brows")
            ]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    scored = {label: e["closeup_images"] for label, e in doc["cases"].items() if "closeup_images" in e}
    if scored:
        lines += [
            "",
            "## The close-ups as images",
            "",
            "Render against target over the trained background (the person mask), whole close-up; "
            "LPIPS-VGG ×1000 (no method trains on it).",
            "",
            "| case | frames | PSNR | LPIPS-VGG ×1000 |",
            "|---|---:|---:|---:|",
        ]
        for label, c in scored.items():
            lines.append(f"| {label} | {c['frames']} | {c['psnr']:.2f} | {1000 * c['lpips_vgg']:.1f} |")
        for group, labels in seed_groups(scored).items():
            got = [scored[label] for label in labels]
            p = fmt(mean_std([c["psnr"] for c in got]))
            lp = fmt(mean_std([1000 * c["lpips_vgg"] for c in got]))
            lines.append(f"| {group} (mean ± std, {len(got)} seeds) | {got[0]['frames']} | {p} | {lp} |")
    lines += seed_summary(doc)
    for label, e in doc["cases"].items():
        if e.get("contact_sheet"):
            lines += [
                "",
                f"### {label}",
                "",
                f"![{label}]({e['contact_sheet']})",
                "",
                "Face close-ups, target | render: the widest-open mouths, then the most closed eyes "
                "of the target.",
            ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--case",
        nargs=3,
        action="append",
        required=True,
        metavar=("LABEL", "DATASET", "AVATAR"),
        help="a dataset and an avatar trained on it ('-': none); repeat for more",
    )
    ap.add_argument("--split", default="test_pose")
    ap.add_argument("--every", type=int, default=1, help="every k-th frame of the split")
    ap.add_argument(
        "--refit",
        action="store_true",
        help="also fit each clip again from its stored detections (stage refitted)",
    )
    ap.add_argument("--blur", type=float, default=0.0, help="px: also the blurred-target control stage")
    ap.add_argument(
        "--closeup", action="store_true", help="the face close-ups at the video's resolution as targets"
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--name", default="expressions")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    doc = {
        **run_header(),
        "cases": {},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    for label, dataset, avatar in args.case:
        entry, images = run_case(
            label,
            Path(dataset),
            None if avatar == "-" else Path(avatar),
            args.split,
            args.every,
            args.refit,
            args.blur,
            args.closeup,
        )
        sheet = contact_sheet(images, picks_of(images["target"]))
        if sheet is not None:
            from PIL import Image

            name = f"{args.name}_{label}.jpg"
            Image.fromarray(sheet).save(args.out / name, quality=85, optimize=True)
            entry["contact_sheet"] = name
        doc["cases"][label] = entry
        write_result(args.out, args.name, doc, markdown(doc))
    print(markdown(doc))


if __name__ == "__main__":
    main()
