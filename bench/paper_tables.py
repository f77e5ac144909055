"""The paper's tables on our data (issue 6): Table 1 (3DGS + body vs EVA) and Table 2 (EVA w/o
CADC, w/o CL, EVA) on the synthetic ``controlled`` preset with ground-truth body parameters (the
XHumans setting), plus a speed-vs-error figure (hand and face LPIPS against wall-clock training
time, and against the Gaussian count) for the baseline and EVA.

    .venv/bin/python bench/paper_tables.py         # the committed tables (2-core CPU, 13 min)
    .venv/bin/python bench/paper_tables.py --preset default --image-scale 1 \
        --methods 3dgs+body eva eva-same-gs --budgets 1 --name paper_tables_512
                                                   # the paper's size (512 px, 2,000 its; 30 min)
    .venv/bin/python bench/paper_tables.py --methods eva eva-no-cl --perturb 0.5 --budgets 1 \
        --name cl_misaligned                       # CL under misalignment (jittered training fits)
    .venv/bin/python bench/paper_tables.py --size tiny --preset tiny --image-scale 1 --budgets 1
                                                   # a smoke run

Methods are ``eva_engine.train.methods.METHODS`` (one config switched by options, no copies),
plus ``eva-same-gs``: EVA with the baseline's final Gaussian count as its budget
(``max_gaussians``), the comparison "at no more Gaussians". Every method trains from the same
preset, seed and frames; the speed curve re-trains the baseline and EVA with the schedule
shortened to each ``--budgets`` fraction (densification window and SH schedule scaled with it):
each point is what that training time buys.

The defaults are what fits this project's machine (2 CPU cores, where 512 px / 2,000 iterations
takes 6 to 13 minutes of training per method): the ``fast`` preset (600 iterations, densification 120..300
every 30, 6,000 seeds) on frames resampled to half size (256 px), every second novel-pose test
frame. Hands are ~20 px wide at that scale.

Writes ``bench/results/paper_tables.json`` (one entry per method: ``n_gaussians``,
``train_seconds``, ``full``/``hand``/``face`` with ``psnr``, ``ssim``, ``lpips``; plus the
configuration, Gaussians per part before/after, and the speed-curve points),
``bench/results/paper_tables.md`` and ``bench/results/speed_vs_error.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from machine import describe

RESULTS = Path(__file__).resolve().parent / "results"
TABLE1 = ("3dgs+body", "eva", "eva-same-gs")
# EVA with the baseline's final Gaussian count as its budget (``max_gaussians``): the comparison
# "at no more Gaussians" (bench-only row; runs right after the baseline).
SAME_GS = "eva-same-gs"
TABLE2 = ("eva-no-cadc", "eva-no-cl", "eva")
EXTRA = ("eva-no-cadc-no-cl", "eva-part-mean")
CURVE_METHODS = ("3dgs+body", "eva")


class ScaledDataset:
    """A dataset resampled by ``scale`` (images, masks and intrinsics), frames cached in memory,
    with the ``test_pose`` split thinned to every ``test_every``-th frame. Trainer and evaluator
    see it as the dataset itself."""

    def __init__(self, dataset, scale: float, test_every: int = 1, train_params=None) -> None:
        self.base, self.scale = dataset, scale
        self.meta, self.params = dataset.meta, dataset.params
        if train_params is not None:  # noisy fits on the training frames, the truth on the others
            train = torch.tensor(dataset.splits["train"])
            mixed = {k: v.clone() for k, v in dataset.params.tensors().items()}
            for k, v in train_params.tensors().items():
                mixed[k][train] = v[train].to(mixed[k].dtype)
            self.params = type(dataset.params)(**mixed)
        self.gt_params = getattr(dataset, "gt_params", None)
        self.splits = dict(dataset.splits)
        self.splits["test_pose"] = dataset.splits["test_pose"][::test_every]
        h, w = dataset.image_size
        self.image_size = (round(h * scale), round(w * scale))
        self._cache: dict[int, object] = {}

    def __len__(self) -> int:
        return len(self.base)

    def _resize(self, x: torch.Tensor | None) -> torch.Tensor | None:
        if x is None or self.scale == 1.0:
            return x
        chw = x.permute(2, 0, 1)[None] if x.ndim == 3 else x[None, None]
        out = F.interpolate(chw, size=self.image_size, mode="area")[0]
        return out.permute(1, 2, 0) if x.ndim == 3 else out[0]

    def __getitem__(self, i: int):
        if i not in self._cache:
            f = self.base[i]
            k = f.K.clone().float()
            k[0] *= self.image_size[1] / self.base.image_size[1]
            k[1] *= self.image_size[0] / self.base.image_size[0]
            r = self._resize
            self._cache[i] = dataclasses.replace(
                f, image=r(f.image), mask=r(f.mask), hand_mask=r(f.hand_mask), face_mask=r(f.face_mask), K=k
            )
        return self._cache[i]


def scaled_schedule(config, fraction: float):
    """``config`` with ``fraction`` times its iterations; densification window and SH schedule
    scaled along (learning rates unchanged)."""
    if fraction == 1.0:
        return config
    s = config.strategy
    strategy = dataclasses.replace(
        s,
        refine_start_iter=max(1, round(s.refine_start_iter * fraction)),
        refine_stop_iter=max(2, round(s.refine_stop_iter * fraction)),
        refine_every=max(1, round(s.refine_every * fraction)),
    )
    return dataclasses.replace(
        config,
        iterations=max(1, round(config.iterations * fraction)),
        strategy=strategy,
        sh_degree_interval=max(1, round(config.sh_degree_interval * fraction)),
    )


def run_method(ds, config, lpips, label: str) -> dict:
    from eva_engine.eval import evaluate_avatar
    from eva_engine.train import train_avatar

    def report(p) -> None:
        if p.stage == "train" and p.iteration % 100 == 0:
            print(f"  [{label}] {p.iteration}/{p.total} loss {p.loss:.4f} GS {p.num_gaussians} "
                  f"{p.elapsed:.0f}s", file=sys.stderr, flush=True)  # fmt: skip

    result = train_avatar(ds, config, progress=report)
    t0 = time.perf_counter()
    ev = evaluate_avatar(result.avatar, ds, lpips=lpips, train_seconds=result.train_seconds)
    eval_seconds = time.perf_counter() - t0
    entry = {
        "n_gaussians": len(result.avatar.gaussians),
        "n_gaussians_initial": sum(result.gaussians_per_part["before"].values()),
        "gaussians_per_part": result.gaussians_per_part["after"],
        "gaussians_per_part_initial": result.gaussians_per_part["before"],
        "train_seconds": result.train_seconds,
        "iterations": config.iterations,
        "eval_seconds": eval_seconds,
        "render_fps": ev.render_fps,
        "final_loss": result.losses[-1],
        "ms_per_iteration_by_stage": {k: 1000 * v / config.iterations for k, v in result.timings.items()},
        "refinements": result.refinements,
    }
    for region, m in ev.regions.items():
        entry[region] = {"psnr": m.psnr, "ssim": m.ssim, "lpips": m.lpips, "frames": m.frames}
    lp = ", ".join(
        f"{r} LPIPS {1000 * entry[r]['lpips']:.1f}" for r in ("full", "hand", "face") if r in entry
    )
    print(f"  [{label}] done: {entry['n_gaussians']} GS, {entry['train_seconds']:.0f}s train, {lp}",
          file=sys.stderr, flush=True)  # fmt: skip
    return entry


def markdown(doc: dict) -> str:
    cfg = doc["config"]
    lines = [
        "# The paper's tables on our data (issue 6)",
        "",
        f"- date: {doc['date']}; command: `{doc['command']}`",
        f"- machine: {doc['machine']}; load average at start {doc['load_start']}, at end {doc['load_end']}",
        f"- data: {cfg['dataset']} resampled to {cfg['image_size'][1]}x{cfg['image_size'][0]} px, "
        f"{cfg['train_frames']} training frames, {cfg['test_frames']} novel-pose test frames "
        + (
            f"(training frames driven by jittered body parameters: the ground truth plus per-frame "
            f"noise of level {cfg['perturb']:g} (data.perturb); test frames by the ground truth)"
            if cfg.get("perturb")
            else "(ground-truth body parameters, XHumans-like)"
        ),
        f"- training: preset `{cfg['preset']}` with its schedule x{cfg.get('schedule', 1.0):g} "
        f"({cfg['iterations']} iterations, densification "
        f"{cfg['refine'][0]}..{cfg['refine'][1]} every {cfg['refine'][2]}), seed {cfg['seed']}, "
        f"{cfg['threads']} threads; total wall time {doc['total_seconds'] / 60:.1f} min",
        "",
        "LPIPS ×1000 (AlexNet), regions cropped to the hand / face mask boxes; time = training loop only.",
        "",
    ]

    def table(title: str, names) -> None:
        head = "| Method | N-GS | " + " | ".join(
            f"{r.capitalize()} PSNR↑ | {r.capitalize()} SSIM↑ | {r.capitalize()} LPIPS↓"
            for r in ("full", "hand", "face")
        )
        lines.extend([f"## {title}", "", head + " | Train (s) |", "|---|---:|" + "---:|" * 10])
        for name in names:
            e = doc["methods"][name]
            cells = [name, f"{e['n_gaussians']:,}"]
            for r in ("full", "hand", "face"):
                m = e.get(r)
                fmt = [f"{m['psnr']:.2f}", f"{m['ssim']:.4f}", f"{1000 * m['lpips']:.2f}"] if m else None
                cells += fmt or ["–"] * 3
            cells.append(f"{e['train_seconds']:.0f}")
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")

    table("Table 1: comparison with the baseline", [m for m in TABLE1 if m in doc["methods"]])
    table("Table 2: ablation of CADC and CL", [m for m in TABLE2 if m in doc["methods"]])
    extra = [m for m in EXTRA if m in doc["methods"]]
    if extra:
        table("Further rows: both contributions off; the official per-part-mean CADC", extra)
    lines += ["## Gaussians per part (body / hand / face), before and after training", ""]
    for name, e in doc["methods"].items():
        fmt = "{body:,} / {hand:,} / {face:,}"
        before, after = e["gaussians_per_part_initial"], e["gaussians_per_part"]
        lines.append(f"- {name}: {fmt.format(**before)} → {fmt.format(**after)}")
    if doc.get("curve"):
        lines += ["", "## Speed vs error (the figure's points)", "",
                  "| Method | budget | iterations | Train (s) | N-GS | Hand LPIPS↓ | Face LPIPS↓ |",
                  "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
        for p in doc["curve"]:
            cells = [p["method"], f"{p['budget']:g}", str(p["iterations"]), f"{p['train_seconds']:.0f}"]
            cells += [
                f"{p['n_gaussians']:,}",
                f"{1000 * p['hand_lpips']:.2f}",
                f"{1000 * p['face_lpips']:.2f}",
            ]
            lines.append("| " + " | ".join(cells) + " |")
        if set(CURVE_METHODS) <= {p["method"] for p in doc["curve"]}:
            lines += ["", f"![speed vs error]({doc['figure']})"]
    if doc.get("findings"):
        lines += ["", "## Findings", "", *doc["findings"]]
    return "\n".join(lines) + "\n"


def figure(doc: dict, path: Path) -> None:
    """Hand and face LPIPS against training time and against the final Gaussian count: the
    baseline's and EVA's curves over the budgets, and the ``eva-same-gs`` run as a point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curve = list(doc["curve"])
    if SAME_GS in doc["methods"]:
        e = doc["methods"][SAME_GS]
        curve.append({"method": SAME_GS, "train_seconds": e["train_seconds"], "n_gaussians": e["n_gaussians"],
                      "hand_lpips": e["hand"]["lpips"], "face_lpips": e["face"]["lpips"]})  # fmt: skip
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    styles = zip((*CURVE_METHODS, SAME_GS), ("o", "s", "*"), ("C0", "C3", "C2"), strict=True)
    for method, marker, color in styles:
        pts = sorted((p for p in curve if p["method"] == method), key=lambda p: p["train_seconds"])
        if not pts:
            continue
        for region, style in (("hand", "-"), ("face", "--")):
            y = [1000 * p[f"{region}_lpips"] for p in pts]
            for ax, key in zip(axes, ("train_seconds", "n_gaussians"), strict=True):
                ax.plot([p[key] for p in pts], y, style, marker=marker, color=color,
                        markersize=10 if marker == "*" else 6, label=f"{method} {region}")  # fmt: skip
    axes[0].set_xlabel("training time (s, wall clock)")
    axes[1].set_xlabel("Gaussians at the end")
    for ax in axes:
        ax.set_ylabel("LPIPS ×1000 (lower is better)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle("Hand and face LPIPS vs training budget (synthetic controlled preset)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, help="eva-dataset with parameters (default: the synthetic one)")
    ap.add_argument("--size", default="bench", help="synthetic size: tiny or bench")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--preset", default="fast", help="training preset: tiny, fast, default (the paper's)")
    ap.add_argument("--iterations", type=int, help="override the preset's iteration count")
    ap.add_argument("--schedule", type=float, default=1.0,
                    help="scale the preset's schedule (iterations, densification window)")  # fmt: skip
    ap.add_argument("--image-scale", type=float, default=0.5, help="resample frames by this factor")
    ap.add_argument("--test-every", type=int, default=2, help="use every n-th novel-pose test frame")
    ap.add_argument("--methods", nargs="+", default=[*dict.fromkeys((*TABLE1, *TABLE2, *EXTRA))],
                    help=f"methods (eva_engine.train.METHODS) and {SAME_GS} (needs 3dgs+body)")  # fmt: skip
    ap.add_argument("--perturb", type=float, default=0.0,
                    help="jitter the training frames' body parameters (level)")  # fmt: skip
    ap.add_argument("--name", default="paper_tables", help="result file stem (.json, .md)")
    ap.add_argument("--replot", action="store_true", help="only rewrite the .md and figure from the .json")
    ap.add_argument("--budgets", nargs="+", type=float, default=[0.25, 0.5, 1.0],
                    help="schedule fractions for the speed curve (1.0 reuses the table runs)")  # fmt: skip
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = ap.parse_args()
    if args.replot:
        doc = json.loads((args.out / f"{args.name}.json").read_text())
        doc["findings"] = findings(doc["methods"])
        save(doc, args.out, args.name)
        return

    from eva_engine.data import load_dataset
    from eva_engine.metrics import LPIPS
    from eva_engine.paths import data_dir
    from eva_engine.train import METHODS, preset, with_method

    unknown = [m for m in args.methods if m not in (*METHODS, SAME_GS)]
    if unknown:
        ap.error(f"unknown methods {unknown}; choose from {METHODS}")
    torch.set_num_threads(args.threads)
    start, load_start = time.perf_counter(), os.getloadavg()
    path = args.dataset
    if path is None:
        from eva_engine.data.synthetic import generate

        path = data_dir() / "synthetic" / f"controlled-{args.size}-seed{args.seed}"
        if not (path / "meta.json").is_file():
            print(f"generating {path} ...", file=sys.stderr)
            generate("controlled", args.size, args.seed, path)
    source = load_dataset(path)
    if source.params is None:
        sys.exit(f"{path} has no body parameters; this benchmark needs the ground-truth setting")
    noisy = None
    if args.perturb > 0:
        from eva_engine.body import load_body_model
        from eva_engine.data.perturb import PerturbConfig, perturb

        # Per-frame jitter only: frames disagree with each other (what CL is for) while the
        # canonical avatar they average to stays consistent with the true test parameters.
        model = load_body_model(source.meta.body_model)
        jitter = PerturbConfig(bias_fraction=0.0)
        noisy = perturb(source.params, args.perturb, model=model, seed=args.seed, config=jitter)
    ds = ScaledDataset(source, args.image_scale, args.test_every, train_params=noisy)
    overrides = {"threads": args.threads, "device": args.device, "seed": args.seed}
    if args.iterations:
        overrides["iterations"] = args.iterations
    base = scaled_schedule(preset(args.preset, **overrides), args.schedule)
    lpips = LPIPS()

    s = base.strategy
    doc = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "command": "python bench/paper_tables.py " + " ".join(sys.argv[1:]),
        "machine": describe(),
        "load_start": [round(x, 2) for x in load_start],
        "config": {
            "dataset": str(path),
            "image_size": list(ds.image_size),
            "image_scale": args.image_scale,
            "train_frames": len(ds.splits["train"]),
            "test_frames": len(ds.splits["test_pose"]),
            "preset": args.preset,
            "schedule": args.schedule,
            "iterations": base.iterations,
            "seed": args.seed,
            "threads": args.threads,
            "refine": [s.refine_start_iter, s.refine_stop_iter, s.refine_every],
            "budgets": args.budgets,
            "perturb": args.perturb,
            "train_config": {
                name: with_method(base, name).to_dict() for name in args.methods if name in METHODS
            },
        },  # fmt: skip
        "methods": {},
        "curve": [],
        "figure": "speed_vs_error.png" if args.name == "paper_tables" else f"{args.name}_speed_vs_error.png",
    }

    # Tables first, then the shorter curve runs, then the further rows: results are written after
    # every run, so an interrupted benchmark keeps what it measured.
    table_names = [m for m in args.methods if m in (*TABLE1, *TABLE2)]
    plan = [(m, 1.0) for m in table_names]
    plan += [(m, b) for m in CURVE_METHODS for b in sorted(args.budgets) if b != 1.0]
    plan += [(m, 1.0) for m in args.methods if m not in table_names]
    for name, budget in plan:
        label = name if budget == 1.0 else f"{name}@{budget:g}"
        print(f"{label} ...", file=sys.stderr, flush=True)
        if name == SAME_GS:
            if "3dgs+body" not in doc["methods"]:
                sys.exit(f"{SAME_GS} needs the 3dgs+body run first (add it to --methods)")
            config = with_method(base, "eva")
            budget_gs = doc["methods"]["3dgs+body"]["n_gaussians"]
            config = dataclasses.replace(
                config, strategy=dataclasses.replace(config.strategy, max_gaussians=budget_gs)
            )
            doc["config"]["train_config"][SAME_GS] = config.to_dict()
        else:
            config = with_method(base, name)
        entry = run_method(ds, scaled_schedule(config, budget), lpips, label)
        if budget == 1.0:
            doc["methods"][name] = entry
        if name in CURVE_METHODS and budget in args.budgets:
            doc["curve"].append({
                "method": name, "budget": budget, "iterations": entry["iterations"],
                "train_seconds": entry["train_seconds"], "n_gaussians": entry["n_gaussians"],
                "hand_lpips": entry["hand"]["lpips"], "face_lpips": entry["face"]["lpips"],
                "full_lpips": entry["full"]["lpips"],
            })  # fmt: skip
        doc["load_end"] = [round(x, 2) for x in os.getloadavg()]
        doc["total_seconds"] = time.perf_counter() - start
        doc["findings"] = findings(doc["methods"])
        save(doc, args.out, args.name)
    print(markdown(doc))


def save(doc: dict, out: Path, name: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(doc, indent=2, default=str))
    if set(CURVE_METHODS) <= {p["method"] for p in doc["curve"]}:
        figure(doc, out / doc["figure"])
    (out / f"{name}.md").write_text(markdown(doc))


def findings(methods: dict) -> list[str]:
    """Plain statements computed from the numbers (no judgement added here)."""
    out = []

    def rel(a: str, b: str, region: str) -> float | None:
        if a in methods and b in methods and region in methods[a] and region in methods[b]:
            return 100.0 * (methods[a][region]["lpips"] / methods[b][region]["lpips"] - 1.0)
        return None

    for a, b in (("eva", "3dgs+body"), (SAME_GS, "3dgs+body"), ("eva", "eva-no-cadc"), ("eva", "eva-no-cl"),
                 ("eva-part-mean", "eva"), ("eva-no-cadc-no-cl", "3dgs+body")):  # fmt: skip
        parts = [f"{r} {v:+.1f}%" for r in ("full", "hand", "face") if (v := rel(a, b, r)) is not None]
        if parts:
            na, nb = methods[a]["n_gaussians"], methods[b]["n_gaussians"]
            out.append(f"- LPIPS of {a} relative to {b}: {', '.join(parts)} (N-GS {na:,} vs {nb:,}).")
    # The goal: >= 15% lower hand and face LPIPS than 3dgs+body at no more Gaussians.
    base = methods.get("3dgs+body")
    for name in ("eva", SAME_GS):
        if base is None or name not in methods:
            continue
        hand, face = rel(name, "3dgs+body", "hand"), rel(name, "3dgs+body", "face")
        fewer = methods[name]["n_gaussians"] <= base["n_gaussians"]
        met = hand is not None and face is not None and hand <= -15 and face <= -15 and fewer
        out.append(f"- goal (hand and face LPIPS >= 15% below 3dgs+body with no more Gaussians) for {name}: "
                   f"{'met' if met else 'not met'} (hand {hand:+.1f}%, face {face:+.1f}%, "
                   f"N-GS {'<=' if fewer else '>'} the baseline's).")  # fmt: skip
    return out


if __name__ == "__main__":
    main()
