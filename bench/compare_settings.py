"""One training setting against another on the synthetic benchmark: the same methods and seeds
trained by ``bench/paper_tables.py`` with and without ``--set`` overrides, compared paired over
the seeds (``stats.compare_paired``: a gap counts only when its mean exceeds its std).

    .venv/bin/python -m bench paper_tables --preset fast --threads 1 --seeds 0 --methods eva \\
        --set loss.lpips_every=2 --out bench/results/speed_quality --name lpips2_seed0   # per seed
    .venv/bin/python -m bench compare_settings --results bench/results/speed_quality \\
        --base exact --settings detach lpips2 --name summary

Reads ``<results>/<name>_seed*.json`` for the base and every setting (one file per seed, as the
seeds run side by side) and writes ``<results>/<name>.md``: per method and setting, what the
setting changes in the train config, its training seconds against the base's, and the paired
gaps in LPIPS-VGG (held out), PSNR and SSIM for the full image, the hands and the face.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from bench.machine import header_line, run_header
from bench.paper_tables import paired_regions, trained_on
from bench.seed_results import load_seeds
from bench.stats import compare_paired, mean_std


def load(results: Path, name: str) -> dict:
    try:
        return load_seeds(results, name)
    except FileNotFoundError as e:
        raise SystemExit(str(e)) from None


def changed(base: dict, other: dict, prefix: str = "") -> list[str]:
    """The train-config fields whose values differ, as 'path: base -> other'."""
    out = []
    for key in sorted(base.keys() | other.keys()):
        a, b = base.get(key), other.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += changed(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"`{prefix}{key}`: {a} -> {b}")
    return out


def markdown(base_name: str, base: dict, settings: dict[str, dict], header: dict) -> str:
    lines = [
        "# Training settings against the base, paired over seeds",
        "",
        header_line(header),
        f"- machine: {base['machine']}",
        *(
            f"- machine of `{name}`: {doc['machine']} (not the base's: its seconds do not compare)"
            for name, doc in settings.items()
            if doc["machine"].split(",")[0] != base["machine"].split(",")[0]
        ),
        f"- base `{base_name}`: `{base['command'].split(' && ')[0]}` (one process per seed)",
        f"- benchmark: synthetic controlled, preset `{base['config']['preset']}`, seeds "
        f"{base['config']['seeds']}; LPIPS-VGG is held out unless a section's 'trains on' says "
        "*trained on the metric*",
        "",
        "Each cell: the setting against the base, the mean ± std over seeds of the per-seed relative "
        "gap; better / worse only when the mean exceeds the std. Train (s): the training loop's wall "
        "time, seeds run two at a time on one thread each (a rough ratio, not a speed benchmark).",
        "",
    ]
    for name, doc in settings.items():
        for method, entry in doc["methods"].items():
            if method not in base["methods"]:
                continue
            mine = {r["seed"]: r for r in entry["runs"]}
            theirs = {r["seed"]: r for r in base["methods"][method]["runs"]}
            seeds = sorted(mine.keys() & theirs.keys())
            if not seeds:
                continue
            what = changed(base["config"]["train_config"][method], doc["config"]["train_config"][method])
            _, time_gap = compare_paired(
                [mine[s]["train_seconds"] for s in seeds], [theirs[s]["train_seconds"] for s in seeds], True
            )
            seconds = mean_std([mine[s]["train_seconds"] for s in seeds])
            base_seconds = statistics.fmean(theirs[s]["train_seconds"] for s in seeds)
            lines += [
                f"## {method}, `{name}`",
                "",
                f"- changes: {', '.join(what) or 'nothing'}",
                f"- trains on: base {trained_on(method, base['config']['train_config'][method])}; "
                f"`{name}` {trained_on(method, doc['config']['train_config'][method])}",
                f"- seeds {seeds}; train {seconds['mean']:.0f} s against {base_seconds:.0f} s "
                f"({time_gap['mean']:+.1f} ± {time_gap['std']:.1f}%)",
                *(f"- {part}" for part in paired_regions(mine, theirs, seeds)),
                "",
            ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, required=True, help="folder of the per-seed result files")
    ap.add_argument("--base", required=True, help="result name of the base setting")
    ap.add_argument("--settings", nargs="+", required=True, help="result names of the other settings")
    ap.add_argument("--name", default="summary", help="markdown file stem")
    args = ap.parse_args(argv)
    base = load(args.results, args.base)
    settings = {name: load(args.results, name) for name in args.settings}
    text = markdown(args.base, base, settings, run_header())
    (args.results / f"{args.name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
