"""Benchmark of avatar training: time per iteration and where it goes (data,
skinning, rasterize, losses, backward, optimizer, densify), total training time, Gaussian count,
and the full / hand / face metrics on the novel-pose frames.

    .venv/bin/python bench/train.py                               # synthetic bench (512 px), paper preset
    .venv/bin/python bench/train.py --size tiny --preset tiny     # seconds, a smoke run
    .venv/bin/python bench/train.py --dataset PATH --preset fast  # any eva-dataset

The dataset is generated once under ``data/synthetic/<preset>-<size>-seed<seed>`` (eva synth's
layout) and reused. Writes ``bench/results/train.json`` (machine-readable, one entry per run
keyed by dataset and preset) and ``bench/results/train.md``. Target (2 CPU cores, 512 px): the
2,000-iteration default run in <= 10 minutes.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path

import torch
from machine import describe

from eva_engine.recipes import METHODS, PRESETS, describe_methods, describe_presets
from eva_engine.synth_names import SYNTH_PRESETS, SYNTH_SIZES, describe_synth_sizes

RESULTS = Path(__file__).resolve().parent / "results"
TARGET_SECONDS = 600.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--dataset", type=Path, help="an existing eva-dataset (default: generate the synthetic one)"
    )
    ap.add_argument(
        "--synthetic",
        default="controlled",
        choices=list(SYNTH_PRESETS),
        help="synthetic preset (controlled has parameters)",
    )
    ap.add_argument("--size", default="bench", choices=list(SYNTH_SIZES), help=describe_synth_sizes())
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--preset", default="default", choices=list(PRESETS), help=describe_presets())
    ap.add_argument("--method", choices=list(METHODS), help=f"default: the preset's; {describe_methods()}")
    ap.add_argument("--iterations", type=int, help="override the preset's iteration count")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, help="also save the avatar here")
    args = ap.parse_args()

    from eva_engine.avatar import save_avatar
    from eva_engine.data import load_dataset
    from eva_engine.eval import evaluate_avatar, metrics_table
    from eva_engine.paths import data_dir
    from eva_engine.train import preset, train_avatar, with_method

    torch.set_num_threads(args.threads)
    path = args.dataset
    if path is None:
        from eva_engine.synth import generate

        path = data_dir() / "synthetic" / f"{args.synthetic}-{args.size}-seed{args.seed}"
        if not (path / "meta.json").is_file():
            print(f"generating {path} ...", file=sys.stderr)
            generate(args.synthetic, args.size, args.seed, path)
    ds = load_dataset(path)
    overrides = {"device": args.device}
    if args.iterations:
        overrides["iterations"] = args.iterations
    config = preset(args.preset, **overrides)
    if args.method:
        config = with_method(config, args.method)
    name = args.preset if not args.method else f"{args.preset}/{args.method}"

    def report(e) -> None:
        if e.stage != "train" or e.done % 100 == 0:
            print(
                f"{e.stage}: {e.message}, {e.elapsed:.0f}s eta {e.eta or 0:.0f}s", file=sys.stderr, flush=True
            )

    result = train_avatar(ds, config, progress=report)
    ev = evaluate_avatar(result.avatar, ds, train_seconds=result.train_seconds)
    if args.out:
        save_avatar(result.avatar, args.out, result.record(config, preset=args.preset), result.frames(ds))
    n = config.iterations
    entry = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "command": "python bench/train.py " + " ".join(sys.argv[1:]),
        "machine": describe(),
        "dataset": str(path),
        "image_size": list(ds.image_size),
        "train_frames": len(ds.splits["train"]),
        "preset": args.preset,
        "method": args.method,
        "iterations": n,
        "train_seconds": result.train_seconds,
        "seconds_per_iteration": result.train_seconds / n,
        "ms_per_iteration_by_stage": {k: 1000 * v / n for k, v in result.timings.items()},
        "num_gaussians": len(result.avatar.gaussians),
        "refinements": result.refinements,
        "final_loss": result.losses[-1],
        "eval": {k: v for k, v in ev.to_dict().items() if k != "per_frame"},
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / "train.json"
    runs = json.loads(json_path.read_text()) if json_path.is_file() else {}
    runs[f"{Path(path).name}/{name}"] = entry
    json_path.write_text(json.dumps(runs, indent=2))
    (RESULTS / "train.md").write_text(markdown(runs, metrics_table))
    print(markdown({f"{Path(path).name}/{name}": entry}, metrics_table))


def region_metrics(v: dict):
    """A stored region entry as ``RegionMetrics``; runs recorded before LPIPS-VGG existed have only
    ``lpips`` (AlexNet): their VGG column is NaN (not measured)."""
    from eva_engine.eval import RegionMetrics

    if "lpips" in v:
        old = {k: x for k, x in v.items() if k != "lpips"}
        v = {**old, "lpips_alex": v["lpips"], "lpips_vgg": float("nan")}
    return RegionMetrics(**v)


def markdown(runs: dict, metrics_table) -> str:
    from eva_engine.eval import EvalResult

    lines = ["# Avatar training benchmark", ""]
    for key, e in runs.items():
        stages = " | ".join(f"{k} {v:.1f}" for k, v in e["ms_per_iteration_by_stage"].items())
        ok = "met" if e["iterations"] >= 2000 and e["train_seconds"] <= TARGET_SECONDS else "n/a or NOT met"
        lines += [
            f"## {key}",
            "",
            f"- date: {e['date']}; command: `{e['command']}`",
            f"- machine: {e['machine']}",
            f"- data: {e['dataset']} ({e['image_size'][1]}x{e['image_size'][0]}, "
            f"{e['train_frames']} training frames)",
            f"- {e['iterations']} iterations in {e['train_seconds']:.1f} s "
            f"({1000 * e['seconds_per_iteration']:.1f} ms/iteration); target 2,000 in <= 10 min: {ok}",
            f"- ms per iteration by stage: {stages}",
            f"- Gaussians at the end: {e['num_gaussians']:,}",
            "",
        ]
        ev = e["eval"]
        res = EvalResult(
            split=ev["split"],
            num_frames=ev["num_frames"],
            num_gaussians=ev["num_gaussians"],
            render_fps=ev["render_fps"],
            train_seconds=ev["train_seconds"],
            regions={k: region_metrics(v) for k, v in ev["regions"].items()},
        )
        lines += [metrics_table({e["preset"]: res}), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
