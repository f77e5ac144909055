"""Benchmark of avatar training: time per iteration and where it goes (data,
skinning, rasterize, losses, backward, optimizer, densify), total training time, Gaussian count,
and the full / hand / face metrics on the novel-pose frames.

    .venv/bin/python -m bench train                               # synthetic bench (512 px), paper preset
    .venv/bin/python -m bench train --size tiny --preset tiny     # seconds, a smoke run
    .venv/bin/python -m bench train --dataset PATH --preset fast  # any eva-dataset

Speed against an earlier commit: run that commit's own bench/train.py from a worktree of it
(``PYTHONPATH=<worktree>``, so its eva_engine is the one imported) and record its entry here with
``--import-run <worktree>/bench/results/train.json --label before``; train.md then gives each
run's speed-up against the run labelled ``before`` with the same dataset, preset and method.

The dataset is generated once under ``data/synthetic/<preset>-<size>-seed<seed>`` (eva synth's
layout) and reused. Writes ``bench/results/train.json`` (machine-readable, one entry per run
keyed by dataset and preset) and ``bench/results/train.md``. Target (2 CPU cores, 512 px): the
2,000-iteration default run in <= 5 minutes, for the default method and for eva.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from bench.machine import commit, header_line, portable, run_header, write_result
from eva_engine.recipes import METHODS, PRESETS, describe_methods, describe_presets
from eva_engine.synth_names import SYNTH_PRESETS, SYNTH_SIZES, describe_synth_sizes

RESULTS = Path(__file__).resolve().parent / "results"
TARGET_SECONDS = 300.0


def main(argv: list[str] | None = None) -> None:
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
    ap.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
        help="train-config fields, e.g. loss.lpips_every=2 (eva_engine.train.with_overrides)",
    )
    ap.add_argument(
        "--profile-at",
        type=int,
        metavar="STEP",
        help="record torch.profiler's per-op times for --profile-steps steps after STEP (their times then "
        "include the profiler's overhead: time runs without it)",
    )
    ap.add_argument("--profile-steps", type=int, default=20)
    ap.add_argument("--label", help="recorded under '<dataset>/<preset>[/<method>]@<label>' (e.g. before)")
    ap.add_argument(
        "--import-run",
        type=Path,
        help="copy the entries of another checkout's train.json here (with --label), then stop",
    )
    args = ap.parse_args(argv)
    from eva_engine.paths import data_dir

    path = args.dataset or data_dir() / "synthetic" / f"{args.synthetic}-{args.size}-seed{args.seed}"
    key = f"{Path(path).name}/{args.preset}" + (f"/{args.method}" if args.method else "")
    if args.import_run:
        # The entry this command made in another checkout (its own bench script, its own code).
        if not args.label:
            ap.error("--import-run needs --label")
        imported = json.loads(args.import_run.read_text())
        if key not in imported:
            ap.error(f"{args.import_run} has no run {key!r}")
        sha = commit(args.import_run.resolve().parents[2])
        save_runs({f"{key}@{args.label}": {"commit": sha, **imported[key], "label": args.label}})
        return
    if args.label:
        key += f"@{args.label}"

    from eva_engine.avatar import save_avatar
    from eva_engine.data import load_dataset
    from eva_engine.eval import evaluate_avatar
    from eva_engine.train import preset, train_avatar, with_method, with_overrides

    torch.set_num_threads(args.threads)
    if not (Path(path) / "meta.json").is_file():
        if args.dataset:
            ap.error(f"{path} is not an eva-dataset (no meta.json)")
        from eva_engine.synth import generate

        print(f"generating {path} ...", file=sys.stderr)
        generate(args.synthetic, args.size, args.seed, path)
    ds = load_dataset(path)
    overrides = {"device": args.device}
    if args.iterations:
        overrides["iterations"] = args.iterations
    config = preset(args.preset, **overrides)
    if args.method:
        config = with_method(config, args.method)
    config = with_overrides(config, args.set)

    def report(e) -> None:
        if e.stage != "train" or e.done % 100 == 0:
            print(
                f"{e.stage}: {e.message}, {e.elapsed:.0f}s eta {e.eta or 0:.0f}s", file=sys.stderr, flush=True
            )

    profiler = StepProfiler(args.profile_at, args.profile_steps) if args.profile_at else None
    result = train_avatar(
        ds,
        config,
        progress=report,
        checkpoint=profiler,
        checkpoint_steps=profiler.steps if profiler else (),
    )
    ev = evaluate_avatar(result.avatar, ds, train_seconds=result.train_seconds)
    if args.out:
        save_avatar(result.avatar, args.out, result.record(config, preset=args.preset), result.frames(ds))
    n = config.iterations
    entry = {
        **run_header(),
        "label": args.label,
        "set": args.set,
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
    if profiler is not None:
        entry["profile"] = profiler.result
    save_runs({key: entry})
    print(markdown({key: entry}))


class StepProfiler:
    """A training checkpoint hook that runs ``torch.profiler`` over ``steps`` training steps after
    step ``start`` and keeps the ops with the most self CPU time, per step."""

    def __init__(self, start: int, steps: int, top: int = 30) -> None:
        from torch.profiler import ProfilerActivity, profile

        self.steps = (start, start + steps)
        self.top = top
        self.result: dict = {}
        self._profile = profile(activities=[ProfilerActivity.CPU])
        self._started = 0.0

    def __call__(self, step: int, avatar, seconds: float) -> None:
        if step == self.steps[0]:
            self._profile.start()
            self._started = time.perf_counter()
            return
        wall = time.perf_counter() - self._started
        self._profile.stop()
        n = self.steps[1] - self.steps[0]
        events = sorted(self._profile.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
        self.result = {
            "after_step": self.steps[0],
            "steps": n,
            "gaussians": len(avatar.gaussians),
            "ms_per_step": 1000 * wall / n,
            "ops": [
                {
                    "name": e.key,
                    "self_ms_per_step": e.self_cpu_time_total / 1000 / n,
                    "total_ms_per_step": e.cpu_time_total / 1000 / n,
                    "calls_per_step": e.count / n,
                }
                for e in events[: self.top]
            ],
        }


def profile_lines(p: dict) -> list[str]:
    """Markdown of a ``StepProfiler`` result."""
    return [
        "",
        f"Profile of {p['steps']} steps after step {p['after_step']} ({p['gaussians']:,} Gaussians, "
        f"{p['ms_per_step']:.0f} ms per step under the profiler): the ops with the most self time.",
        "",
        "| op | self ms/step | total ms/step | calls/step |",
        "|---|---:|---:|---:|",
        *(
            f"| `{o['name']}` | {o['self_ms_per_step']:.1f} | {o['total_ms_per_step']:.1f} | "
            f"{o['calls_per_step']:.0f} |"
            for o in p["ops"]
        ),
    ]


def save_runs(new: dict) -> None:
    """Merge entries into train.json (one per key) and rewrite train.md from all of them."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / "train.json"
    runs = json.loads(json_path.read_text()) if json_path.is_file() else {}
    runs = portable({**runs, **new})  # the new entries' paths too, in the Markdown as in the JSON
    write_result(RESULTS, "train", runs, markdown(runs))


def speedups(runs: dict) -> list[str]:
    """Markdown lines: each unlabelled run against the ``before`` run of its dataset, preset and
    method (training seconds and ms per iteration by stage)."""
    before = {k.split("@")[0]: e for k, e in runs.items() if e.get("label") == "before"}
    rows = []
    for key, e in runs.items():
        b = before.get(key)
        if e.get("label") or b is None:
            continue
        stages = ", ".join(
            f"{k} {b['ms_per_iteration_by_stage'][k]:.0f} -> {v:.0f}"
            for k, v in e["ms_per_iteration_by_stage"].items()
            if k in b["ms_per_iteration_by_stage"] and k != "data"
        )
        rows.append(
            f"| {key} | {b.get('commit') or '?'} | {e.get('commit') or '?'} | {b['train_seconds']:.0f} | "
            f"{e['train_seconds']:.0f} | {b['train_seconds'] / e['train_seconds']:.2f}x | "
            f"{b['num_gaussians']:,} / {e['num_gaussians']:,} | {stages} |"
        )
    if not rows:
        return []
    return [
        "## Speed-up against the runs labelled `before`",
        "",
        "Training wall time of the same command before and after (ms per iteration by stage, before -> "
        "after); Gaussians at the end, before / after.",
        "",
        "| run | before | after | before s | after s | speed-up | Gaussians | ms/iteration by stage |",
        "|---|---|---|---:|---:|---:|---:|---|",
        *rows,
        "",
    ]


def region_metrics(v: dict):
    """A stored region entry as ``RegionMetrics``; runs recorded before LPIPS-VGG existed have only
    ``lpips`` (AlexNet): their VGG column is NaN (not measured)."""
    from eva_engine.eval import RegionMetrics

    if "lpips" in v:
        old = {k: x for k, x in v.items() if k != "lpips"}
        v = {**old, "lpips_alex": v["lpips"], "lpips_vgg": float("nan")}
    return RegionMetrics(**v)


def markdown(runs: dict) -> str:
    from eva_engine.eval import EvalResult, metrics_table

    lines = ["# Avatar training benchmark", "", *speedups(runs)]
    for key, e in runs.items():
        stages = " | ".join(f"{k} {v:.1f}" for k, v in e["ms_per_iteration_by_stage"].items())
        ok = "met" if e["iterations"] >= 2000 and e["train_seconds"] <= TARGET_SECONDS else "n/a or NOT met"
        target = f"target 2,000 in <= {TARGET_SECONDS / 60:.0f} min: {ok}"
        lines += [
            f"## {key}",
            "",
            header_line(e),
            f"- machine: {e['machine']}",
            f"- data: {e['dataset']} ({e['image_size'][1]}x{e['image_size'][0]}, "
            f"{e['train_frames']} training frames)",
            f"- {e['iterations']} iterations in {e['train_seconds']:.1f} s "
            f"({1000 * e['seconds_per_iteration']:.1f} ms/iteration); {target}",
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
        if "profile" in e:
            lines += [*profile_lines(e["profile"]), ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
