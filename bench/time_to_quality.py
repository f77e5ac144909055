"""Time to quality: LPIPS-VGG (full, hand, face) on the novel-pose frames against training
wall-seconds, for ``3dgs+body`` and ``eva``, on the paper tables' synthetic benchmark (the same
subjects, seeds and preset), mean ± std over seeds.

    .venv/bin/python -m bench time_to_quality                       # 3 seeds, fast preset
    .venv/bin/python -m bench time_to_quality --seeds 1 --name time_to_quality_seed1   # one seed
    .venv/bin/python -m bench time_to_quality --merge time_to_quality_seed0 time_to_quality_seed1 ...

Each run trains once and is evaluated at its checkpoints (``train_avatar(checkpoint=...)``: the
avatar as it trains, before the end-of-training pruning, so the last point can differ slightly
from the paper table's row); the seconds are training seconds, evaluation excluded. Runs are
written as they finish and a re-run skips the runs it has (resumable).

Writes ``bench/results/<name>.json``, ``<name>.md`` and ``<name>.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from bench.machine import header_line, resumable, run_header, write_result
from bench.paper_tables import dataset_for
from bench.stats import fmt, mean_std
from eva_engine.recipes import METHODS, PRESETS
from eva_engine.synth_names import SYNTH_SIZES

RESULTS = Path(__file__).resolve().parent / "results"
REGIONS = ("full", "hand", "face")
DEFAULT_METHODS = ("3dgs+body", "eva")


def checkpoints_for(iterations: int, count: int = 5) -> list[int]:
    """``count`` steps spread over the run, denser early (where the curve moves), the last one
    the end."""
    steps = {max(1, round(iterations * (k / count) ** 1.5)) for k in range(1, count + 1)}
    return sorted(steps)


def run_one(ds, method: str, preset_name: str, seed: int, metrics, split: str) -> dict:
    from eva_engine.eval import evaluate_avatar
    from eva_engine.train import preset, train_avatar, with_method

    config = with_method(preset(preset_name, seed=seed), method)
    points = []

    def evaluate(step: int, avatar, seconds: float) -> None:
        ev = evaluate_avatar(avatar, ds, split=split, metrics=metrics)
        point = {"step": step, "train_seconds": seconds, "n_gaussians": len(avatar.gaussians)}
        point.update({r: {"lpips_vgg": m.lpips_vgg, "psnr": m.psnr} for r, m in ev.regions.items()})
        points.append(point)
        print(
            f"  [{method} seed {seed}] step {step}: {seconds:.0f} s, full LPIPS-VGG "
            f"{1000 * point['full']['lpips_vgg']:.1f}",
            file=sys.stderr,
            flush=True,
        )

    steps = checkpoints_for(config.iterations)
    result = train_avatar(ds, config, checkpoint=evaluate, checkpoint_steps=tuple(steps))
    return {
        "method": method,
        "seed": seed,
        "train_seconds": result.train_seconds,
        "pose_correction": config.pose_correction.enabled,
        "points": points,
    }


def curves(runs: list[dict]) -> dict:
    """method -> list over checkpoints of {step, seconds, region: LPIPS-VGG} mean ± std."""
    out = {}
    for method in dict.fromkeys(r["method"] for r in runs):
        mine = [r for r in runs if r["method"] == method]
        steps = [p["step"] for p in mine[0]["points"]]
        rows = []
        for i, step in enumerate(steps):
            pts = [r["points"][i] for r in mine if len(r["points"]) > i]
            seconds = mean_std([p["train_seconds"] for p in pts])
            row = {"step": step, "seeds": len(pts), "train_seconds": seconds}
            for region in REGIONS:
                vals = [p[region]["lpips_vgg"] for p in pts if region in p]
                if vals:
                    row[region] = mean_std(vals)
            rows.append(row)
        out[method] = rows
    return out


def markdown(doc: dict) -> str:
    cfg = doc["config"]
    lines = [
        "# Time to quality",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- synthetic `controlled` benchmark ({cfg['size']}), preset `{cfg['preset']}`, seeds "
        f"{', '.join(map(str, cfg['seeds']))}, {cfg['threads']} threads; LPIPS-VGG ×1000 on every "
        f"{cfg.get('eval_every', 1)}-th novel-pose frame (held out: no method trains on it), mean ± std "
        "over seeds; seconds are training wall-seconds, evaluation excluded",
        *([f"- note: {doc['note']}"] if doc.get("note") else []),
        "",
        f"![LPIPS-VGG against training seconds]({doc['figure']})",
        "",
        "| method | step | seeds | train (s) | full LPIPS-VGG↓ | hand LPIPS-VGG↓ | face LPIPS-VGG↓ |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for method, rows in doc["curves"].items():
        for row in rows:
            cells = [method, str(row["step"]), str(row["seeds"]), fmt(row["train_seconds"], digits=0)]
            cells += [fmt(row[r], 1000, 1) if r in row else "–" for r in REGIONS]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
    for ax, region in zip(axes, REGIONS, strict=True):
        for method, rows in doc["curves"].items():
            rows = [r for r in rows if region in r]
            x = [r["train_seconds"]["mean"] for r in rows]
            y = [1000 * r[region]["mean"] for r in rows]
            err = [1000 * r[region]["std"] for r in rows]
            ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=method)
        ax.set_title(f"{region}")
        threads = doc["config"]["threads"]
        ax.set_xlabel(f"training seconds ({threads} torch thread(s), 2-core machine)")
        ax.set_ylabel("LPIPS-VGG ×1000 (lower is better)")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(doc: dict, out: Path, name: str) -> None:
    doc["curves"] = curves(doc["runs"])
    doc["figure"] = f"{name}.png"
    write_result(out, name, doc, markdown(doc))
    plot(doc, out / f"{name}.png")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--size", default="bench", choices=list(SYNTH_SIZES), help="synthetic size (the paper tables': bench)"
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--preset", default="fast", choices=list(PRESETS))
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=list(METHODS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--eval-every", type=int, default=4, help="score every k-th novel-pose frame at each checkpoint"
    )
    ap.add_argument("--name", default="time_to_quality", help="result file stem")
    ap.add_argument("--merge", nargs="+", metavar="NAME", help="only combine the runs of result files")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--note", help="recorded with the results and printed under the settings")
    args = ap.parse_args(argv)
    path = args.out / f"{args.name}.json"
    if args.merge:
        docs = [json.loads((args.out / f"{n}.json").read_text()) for n in args.merge]
        doc = {**docs[0], "command": run_header()["command"]}
        doc["runs"] = [r for d in docs for r in d["runs"]]
        doc["config"] = {**docs[0]["config"], "seeds": sorted({r["seed"] for r in doc["runs"]})}
        doc["machine"] = " / ".join(dict.fromkeys(d["machine"] for d in docs))
        doc["note"] = args.note or docs[0].get("note")
        write(doc, args.out, args.name)
        print(markdown(doc))
        return

    from eva_engine.data import load_dataset
    from eva_engine.eval import ImageMetrics

    torch.set_num_threads(args.threads)
    config = {
        "size": args.size,
        "preset": args.preset,
        "threads": args.threads,
        "seeds": args.seeds,
        "eval_every": args.eval_every,
    }
    doc = resumable(json.loads(path.read_text()) if path.is_file() else {}, path) or {"runs": []}
    if doc.get("config", config) | {"seeds": args.seeds} != config:
        raise SystemExit(f"{path} holds runs of other settings ({doc['config']}); pass another --name")
    doc.update(
        **run_header(),
        config=config,
        note=args.note,
    )
    metrics = ImageMetrics()
    for seed in args.seeds:
        ds = load_dataset(dataset_for(args.size, seed))
        # A checkpoint scores a fixed subset of the novel-pose frames (LPIPS-VGG on CPU is slow).
        ds.splits["time_to_quality"] = ds.splits["test_pose"][:: args.eval_every]
        for method in args.methods:
            if any(r["method"] == method and r["seed"] == seed for r in doc["runs"]):
                continue
            print(f"seed {seed}: {method} ...", file=sys.stderr, flush=True)
            doc["runs"].append(run_one(ds, method, args.preset, seed, metrics, "time_to_quality"))
            write(doc, args.out, args.name)
    write(doc, args.out, args.name)
    print(markdown(doc))


if __name__ == "__main__":
    main()
