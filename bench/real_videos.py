"""The real-video table: the product (preprocess -> train -> eval) on every video of a folder,
with the paper's UPB protocol, for 3dgs+body and EVA, and a contact sheet per video.

    .venv/bin/python -m bench real_videos                    # ../shared/reference/videos (skips if absent)
    .venv/bin/python -m bench real_videos --videos DIR --preset fast --name real_videos_fast
    .venv/bin/python -m bench real_videos --only latentsync_demo3_gesturing --max-size 960 ...

Protocol (the paper's UPB split): each video is sampled to about ``--frames`` frames (every k-th
frame), scaled so its long side is ``--max-size`` px, and alternate frames train and test
(``eva preprocess --test-every 2``). Camera, masks, keypoints, body fit and the region masks
(each hand and the face: the fitted body's parts rendered with the frame's camera, intersected
with the person mask, for the hands and face the detector found) all come from the product's own
preprocessing; there is no ground truth. Each method trains with the same preset and seed, and
is evaluated on the test frames against the person composited on white.

Writes ``bench/results/<name>.json`` (``{"videos": {file: {"frames": {"train", "test"},
"methods": {method: {"n_gaussians", "train_seconds", "full" | "hand" | "face": {"psnr", "ssim",
"lpips_vgg", "lpips_alex"}}}}}}`` plus settings and counts), ``<name>.md`` and one JPEG contact
sheet per video, ``<name>_<video>.jpg``: for 5 test frames, input | target | one render per
method | the same for a close-up of the larger hand in view.

A second protocol, never mixed with the first in one table: ``--refine-poses N`` refines each
test frame's pose for N steps against its image with the avatar frozen before scoring
(``eva_engine.eval.PoseRefinement``); with ``--reuse`` it scores the avatars an earlier run saved
in ``--work`` instead of training them again:

    .venv/bin/python -m bench real_videos --preset fast --reuse --refine-poses 20 --name real_videos_refined

A setting against the default: ``--set FIELD=VALUE ...`` (dotted train-config fields, as in
``bench/paper_tables.py``) trains every method with it; its avatars are kept apart
(``avatar-<method>-<name>``), and ``bench/real_videos_compare.py`` pairs the runs by seed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, run_header, write_result
from eva_engine.recipes import METHODS, PRESETS

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_VIDEOS = Path(__file__).resolve().parents[2] / "shared" / "reference" / "videos"
VIDEO_SUFFIXES = (".mp4", ".mov", ".webm", ".mkv", ".avi")
DEFAULT_METHODS = ("3dgs+body", "eva")
REGIONS = ("full", "hand", "face")
METRICS = ("psnr", "ssim", "lpips_vgg", "lpips_alex")


def list_videos(folder: Path) -> list[Path]:
    """The videos directly in ``folder``, sorted; none when it is not a folder."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.glob("*") if p.suffix.lower() in VIDEO_SUFFIXES)


def videos_or_skip(folder: Path) -> list[Path]:
    """``list_videos(folder)``; when there are none, says why the benchmark skips (stderr)."""
    videos = list_videos(folder)
    if not videos:
        print(
            f"skipping: no videos in {folder} (the reference videos sit in ../shared beside a "
            "checkout; pass --videos DIR)",
            file=sys.stderr,
        )
    return videos


def frame_count(video: Path) -> int:
    import av

    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        if stream.frames:
            return int(stream.frames)
        return sum(1 for _ in container.decode(stream))


def preprocess(video: Path, out: Path, frames: int, max_size: int, detect_max_size: int) -> dict:
    """The dataset of ``video`` (reused when it exists with these settings); returns its report."""
    from eva_engine.align import PreprocessConfig, preprocess_video

    every = max(1, math.ceil(frame_count(video) / frames))
    settings = {"every": every, "max_size": max_size, "test_every": 2, "frames": frames}
    if detect_max_size != max_size:  # datasets made before detection had its own size: the same
        settings["detect_max_size"] = detect_max_size
    stamp = out.with_name("dataset-settings.json")
    if (out / "meta.json").is_file() and stamp.is_file() and json.loads(stamp.read_text()) == settings:
        return json.loads(out.with_name("preprocess-report.json").read_text())
    config = PreprocessConfig(
        every=every, max_frames=frames, max_size=max_size, detect_max_size=detect_max_size, test_every=2
    )
    started = time.perf_counter()
    report = preprocess_video(video, out, config, overwrite=True).to_json()
    report["seconds_total"] = time.perf_counter() - started
    out.with_name("preprocess-report.json").write_text(json.dumps(report, indent=1))
    stamp.write_text(json.dumps(settings))
    return report


def same_settings(saved: dict, wanted: dict) -> bool:
    """Whether a saved train config has ``wanted``'s values (fields added to the config since it
    was saved, e.g. a cache size, are not compared)."""
    if not isinstance(saved, dict) or not isinstance(wanted, dict):
        return saved == wanted
    return all(k not in saved or same_settings(saved[k], v) for k, v in wanted.items())


def train_and_eval(
    ds,
    method: str,
    preset_name: str,
    seed: int,
    metrics,
    out: Path,
    refinement,
    reuse: bool,
    overrides: Sequence[str] = (),
    every: int = 1,
) -> tuple:
    """Train ``method`` (or, with ``reuse``, load the avatar an earlier run saved in ``out`` with
    the same settings) and evaluate it: (table entry, avatar, ``EvalResult``). ``overrides``:
    dotted train-config fields (``train.with_overrides``); ``every``: score every k-th test frame.
    The avatar is scored on the background it trained on (the dataset's white unless its config
    names one: ``eva-official`` trains on black, as its authors score it)."""
    from eva_engine.avatar import load_saved_avatar, save_avatar
    from eva_engine.eval import evaluate_avatar
    from eva_engine.train import train_avatar

    config = method_config(method, preset_name, overrides, seed)
    entry: dict = {"iterations": config.iterations}
    if reuse and (out / "avatar.json").is_file():
        saved = load_saved_avatar(out)
        if not same_settings(saved.meta.train_config or {}, json.loads(json.dumps(config.to_dict()))):
            raise SystemExit(f"{out} was trained with other settings; drop --reuse to train again")
        avatar, train_seconds = saved.avatar, saved.meta.train_seconds
        entry["reused"] = str(out)
    else:

        def report(e) -> None:
            if e.stage == "train" and e.done % 200 == 0:
                print(f"  [{method}] {e.message}, {e.elapsed:.0f}s", file=sys.stderr, flush=True)

        result = train_avatar(ds, config, progress=report)
        avatar, train_seconds = result.avatar, result.train_seconds
        save_avatar(avatar, out, result.record(config, preset=preset_name, method=method))
        entry["gaussians_per_part"] = result.gaussians_per_part
    background = training_background(config)
    ev = evaluate_avatar(
        avatar,
        ds,
        metrics=metrics,
        background=background,
        train_seconds=train_seconds,
        refinement=refinement,
        every=every,
    )
    entry.update(n_gaussians=len(avatar.gaussians), train_seconds=train_seconds, notes=ev.notes)
    entry["eval_background"] = background.tolist() if background is not None else "dataset"
    entry["eval_every"] = every
    entry["trained_on_metric"] = trains_on_vgg(config)
    for region, m in ev.regions.items():
        entry[region] = {k: getattr(m, k) for k in (*METRICS, "frames", "crops", "box_px", "silhouette_iou")}
    entry["placement"] = {r: p for r in ("hand", "face") if (p := ev.placement(r)) is not None}
    return entry, avatar, ev


def method_config(method: str, preset_name: str, overrides: Sequence[str] = (), seed: int = 0):
    """The train config of ``method`` on ``preset_name`` with the dotted ``overrides``."""
    from eva_engine.train import preset, with_method, with_overrides

    return with_overrides(with_method(preset(preset_name, seed=seed), method), list(overrides))


def avatar_dir(folder: Path, method: str, name: str, overrides: Sequence[str]) -> Path:
    """Where a method's avatar is saved in a video's work folder (apart per ``--name`` when the
    run sets train-config fields)."""
    return folder / ("avatar-" + method.replace("+", "_") + (f"-{name}" if overrides else ""))


def trains_on_vgg(config) -> bool:
    """Whether ``config``'s objective has an LPIPS-VGG term (the headline metric)."""
    return config.loss.lambda_lpips > 0 and config.loss.lpips_net == "vgg"


def training_background(config) -> torch.Tensor | None:
    """The background ``config`` trains on: [3], or None for the dataset's."""
    return torch.tensor(config.background, dtype=torch.float32) if config.background is not None else None


def contact_sheet(
    ds, avatars: dict, params: dict, indices: list[int], backgrounds: dict | None = None, tile: int = 192
) -> np.ndarray:
    """Rows of [input | target | render per method | hand close-ups of target and renders];
    ``params``: method -> the body parameters its renders use (the protocol's poses);
    ``backgrounds``: method -> [3] background it renders on (default white, as the target)."""
    import cv2

    from eva_engine.avatar import Camera
    from eva_engine.train.losses import composite_target

    white = torch.ones(3)
    rows = []
    for i in indices:
        f = ds[i]
        h, w = f.image.shape[:2]
        cam = Camera(f.K.float(), f.viewmat.float(), w, h)
        target = composite_target(f.image, f.mask, white)
        with torch.no_grad():
            renders = [
                a(params[m][i], cam, (backgrounds or {}).get(m, white)).image.clamp(0, 1)
                for m, a in avatars.items()
            ]
        full = [f.image, target, *renders]
        # The larger hand in view (by mask area), padded by half its size, for finger detail.
        hands = [f.regions[r] for r in ("hand_left", "hand_right") if r in f.regions]
        hand = max(hands, key=lambda m: float(m.sum()), default=None)
        if hand is not None and float(hand.sum()) > 0:
            ys, xs = torch.nonzero(hand > 0.5, as_tuple=True)
            cx, cy = float(xs.float().mean()), float(ys.float().mean())
            side = int(1.5 * max(int(xs.max() - xs.min()), int(ys.max() - ys.min()), 16))
            x0, y0 = (
                int(np.clip(cx - side / 2, 0, max(w - side, 0))),
                int(np.clip(cy - side / 2, 0, max(h - side, 0))),
            )
            close = [img[y0 : y0 + side, x0 : x0 + side] for img in (target, *renders)]
        else:
            close = [torch.ones(tile, tile, 3) for _ in range(1 + len(renders))]
        scale = tile / h
        tiles = [
            cv2.resize(
                (img.numpy() * 255).round().astype(np.uint8),
                (round(w * scale), tile),
                interpolation=cv2.INTER_AREA,
            )
            for img in full
        ]
        tiles += [
            cv2.resize(
                (img.numpy() * 255).round().astype(np.uint8), (tile, tile), interpolation=cv2.INTER_CUBIC
            )
            for img in close
        ]
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def markdown(doc: dict) -> str:
    cfg = doc["config"]
    detect = cfg.get("detect_max_size", cfg["max_size"])
    lines = [
        "# The real-video table (UPB protocol)",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- protocol: each video sampled to about {cfg['frames']} frames (every k-th), long side "
        f"{cfg['max_size']} px (the detector's frames: up to {detect} px), "
        "alternate frames train / test (`eva preprocess --test-every 2`); "
        f"preset `{cfg['preset']}` ({cfg['iterations']} iterations), seed {cfg['seed']}, "
        f"{cfg['threads']} threads",
        f"- poses of the test frames: {cfg.get('protocol', 'fitted poses')}",
        *([f"- train-config overrides: `{' '.join(cfg['set'])}`"] if cfg.get("set") else []),
        "",
        "LPIPS ×1000. LPIPS-VGG is held out except for the rows marked *trained on the metric* "
        "(`eva-official` trains on LPIPS-VGG, as its authors' code does); the other EVA rows train on "
        "LPIPS-Alex, 3dgs+body on L1 + D-SSIM. Targets: the person composited on the background the "
        "method trained on (white; black for `eva-official`, as its authors score it); region boxes "
        "from the region masks of the product's own preprocessing (each hand its own box, the "
        "face's box). One seed per file: `bench/real_videos_compare.py` gives mean ± std over seeds.",
        "",
        "| video | frames train / test | method | N-GS | Train (s) | "
        + " | ".join(
            f"{r.capitalize()} {c}" for r in REGIONS for c in ("PSNR↑", "SSIM↑", "LPIPS-VGG↓", "LPIPS-Alex↓")
        )
        + " | hand / face frames |",
        "|---|---|---|---:|---:|" + "---:|" * 12 + "---|",
    ]
    for video, v in doc["videos"].items():
        for method, e in v["methods"].items():
            frames = f"{v['frames']['train']} / {v['frames']['test']}"
            # Entries written before they recorded it: derived from the method's config.
            on_metric = e.get("trained_on_metric")
            if on_metric is None:
                on_metric = trains_on_vgg(method_config(method, cfg["preset"], cfg.get("set", [])))
            label = f"{method} (*trained on the metric*)" if on_metric else method
            cells = [video, frames, label, f"{e['n_gaussians']:,}", f"{e['train_seconds']:.0f}"]
            for r in REGIONS:
                m = e.get(r)
                cells += (
                    [f"{m['psnr']:.2f}", f"{m['ssim']:.4f}"]
                    + [f"{1000 * m['lpips_vgg']:.1f}", f"{1000 * m['lpips_alex']:.1f}"]
                    if m
                    else ["–"] * 4
                )
            counts = " / ".join(str(e[r]["frames"]) if r in e else "0" for r in ("hand", "face"))
            lines.append("| " + " | ".join(cells) + f" | {counts} |")
    lines += ["", "## Per video", ""]
    for video, v in doc["videos"].items():
        pre = v["preprocess"]
        rates = ", ".join(f"{k} {x:.0%}" for k, x in pre["detection_rates"].items())
        boxes = {r: e[r]["box_px"] for e in v["methods"].values() for r in ("hand", "face") if r in e}
        lines += [
            f"### {video}",
            "",
            f"- frames kept {pre['kept_frames']} of {pre['decoded_frames']} decoded; found: {rates}",
            "- region sizes (median box side): " + ", ".join(f"{r} {b:.0f} px" for r, b in boxes.items()),
            f"- preprocessing {pre['seconds_total']:.0f} s",
            *[f"- note ({m}): {n}" for m, e in v["methods"].items() for n in e.get("notes", [])],
            *placement_lines(v["methods"]),
            "",
            f"![{video}]({v['contact_sheet']})",
            "",
            "Columns: input | target | "
            + " | ".join(v["methods"])
            + " | hand close-ups: target | "
            + " | ".join(v["methods"])
            + " (the target on white; each render on the background its method trained on).",
            "",
        ]
    return "\n".join(lines) + "\n"


def placement_lines(methods: dict) -> list[str]:
    """Per method and region: silhouette IoU of render and person mask in the crops, and the
    LPIPS-VGG of the crops placed at least as well as the median against the rest."""
    out = []
    for m, e in methods.items():
        for r, p in e.get("placement", {}).items():
            out.append(
                f"- placement ({m}, {r}): silhouette IoU {p['iou_mean']:.2f} mean over {p['crops']} crops; "
                f"LPIPS-VGG ×1000 {1000 * p['lpips_vgg_iou_above']:.0f} at IoU ≥ {p['iou_median']:.2f} "
                f"(median), {1000 * p['lpips_vgg_iou_below']:.0f} below; rank correlation "
                f"{p['rank_correlation']:+.2f}"
            )
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--videos", type=Path, default=DEFAULT_VIDEOS, help="folder of videos")
    ap.add_argument("--only", nargs="+", metavar="STEM", help="only the videos of these file stems")
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=list(METHODS))
    ap.add_argument("--preset", default="default", choices=list(PRESETS))
    ap.add_argument("--frames", type=int, default=280, help="frames to sample per video (train + test)")
    ap.add_argument("--max-size", type=int, default=512, help="long side in pixels")
    ap.add_argument(
        "--detect-max-size", type=int, default=1280, help="long side of the frames the detector sees"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval-every", type=int, default=1, help="score every k-th test frame")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--name", default="real_videos", help="result file stem")
    ap.add_argument("--work", type=Path, help="datasets and avatars (default: <data dir>/real_videos)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument(
        "--refine-poses", type=int, default=0, help="second protocol: test poses refined N steps (0: off)"
    )
    ap.add_argument("--reuse", action="store_true", help="score the avatars saved in --work (same settings)")
    ap.add_argument(
        "--sheet-only",
        action="store_true",
        help="only the contact sheets, of the avatars saved in --work (no training, no scores)",
    )
    ap.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
        help="train-config fields for every method, e.g. pose_correction.enabled=true "
        "(train.with_overrides); the avatars are saved under avatar-<method>-<name>",
    )
    args = ap.parse_args(argv)
    videos = videos_or_skip(args.videos)
    if args.only:
        missing = set(args.only) - {v.stem for v in videos}
        if missing:
            raise SystemExit(f"no video {sorted(missing)} in {args.videos}")
        videos = [v for v in videos if v.stem in args.only]
    if not videos:
        return

    from eva_engine.data import load_dataset
    from eva_engine.eval import ImageMetrics, PoseRefinement
    from eva_engine.eval.evaluate import FITTED_POSES
    from eva_engine.paths import data_dir
    from eva_engine.train import preset

    torch.set_num_threads(args.threads)
    work = args.work or data_dir() / "real_videos"
    metrics = ImageMetrics()
    refinement = PoseRefinement(steps=args.refine_poses) if args.refine_poses else None
    doc = {
        **run_header(),
        "config": {
            "frames": args.frames,
            "max_size": args.max_size,
            "detect_max_size": args.detect_max_size,
            "preset": args.preset,
            "seed": args.seed,
            "threads": args.threads,
            "iterations": preset(args.preset).iterations,
            "methods": args.methods,
            "protocol": refinement.protocol if refinement else FITTED_POSES,
            "eval_every": args.eval_every,
            "set": args.set,
        },
        "videos": {},
    }
    for video in videos:
        print(f"{video.name}: preprocessing ...", file=sys.stderr, flush=True)
        folder = work / video.stem
        pre = preprocess(video, folder / "dataset", args.frames, args.max_size, args.detect_max_size)
        ds = load_dataset(folder / "dataset")
        entry = {
            "frames": {"train": len(ds.splits["train"]), "test": len(ds.splits["test_pose"])},
            "image_size": list(ds.image_size),
            "preprocess": pre,
            "methods": {},
        }
        avatars, poses = {}, {}
        if args.sheet_only:
            from eva_engine.avatar import load_saved_avatar

            for method in args.methods:
                saved = avatar_dir(folder, method, args.name, args.set)
                if not (saved / "avatar.json").is_file():
                    raise SystemExit(f"no saved avatar {saved}: train it first (drop --sheet-only)")
                avatars[method], poses[method] = load_saved_avatar(saved).avatar, ds.params
            entry.pop("methods")
        for method in args.methods if not args.sheet_only else ():
            print(f"{video.name}: {method} ...", file=sys.stderr, flush=True)
            entry["methods"][method], avatars[method], ev = train_and_eval(
                ds,
                method,
                args.preset,
                args.seed,
                metrics,
                avatar_dir(folder, method, args.name, args.set),
                refinement,
                args.reuse,
                args.set,
                args.eval_every,
            )
            poses[method] = ev.refined_params if ev.refined_params is not None else ds.params
        test = ds.splits["test_pose"]
        picks = [test[i] for i in np.linspace(0, len(test) - 1, 5).round().astype(int)]
        backgrounds = {
            m: bg
            for m in avatars
            if (bg := training_background(method_config(m, args.preset, args.set))) is not None
        }
        sheet = contact_sheet(ds, avatars, poses, picks, backgrounds)
        name = f"{args.name}_{video.stem}.jpg"
        from PIL import Image

        args.out.mkdir(parents=True, exist_ok=True)
        Image.fromarray(sheet).save(args.out / name, quality=82, optimize=True)
        print(f"wrote {args.out / name}", file=sys.stderr)
        entry["contact_sheet"] = name
        entry["contact_sheet_frames"] = picks
        if args.sheet_only:
            continue
        doc["videos"][video.name] = entry
        write_result(args.out, args.name, doc, markdown(doc))
    if doc["videos"]:
        print(markdown(doc))


if __name__ == "__main__":
    main()
