"""Real-video runs over seeds: mean ± std per video, method and region, and a comparison of two
sets of runs (``--before`` against ``--after``, e.g. the same method before and after a change
to the engine), paired by seed.

    .venv/bin/python -m bench real_videos_compare --method eva \\
        --before real_videos real_videos_eva_seed1 real_videos_eva_seed2 \\
        --after real_videos_expr_seed0 real_videos_expr_seed1 real_videos_expr_seed2 \\
        --name real_videos_expr

Two methods on the same datasets: ``--before-method 3dgs+body --method eva`` reads the before
runs' 3dgs+body rows and the after runs' eva rows.

Each stem names a ``bench/results/<stem>.json`` written by ``bench/real_videos.py`` (one seed
each; the seeds are read from the files and must match pairwise). The verdicts follow
``stats.compare_paired``: better / worse only when the mean per-seed gap exceeds its standard
deviation, otherwise "no difference". Writes ``<name>.json`` and ``<name>.md``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench.machine import header_line, run_header, write_result
from bench.stats import compare_paired, fmt, mean_std

RESULTS = Path(__file__).resolve().parent / "results"
REGIONS = ("full", "hand", "face")
LOWER_IS_BETTER = {"psnr": False, "ssim": False, "lpips_vgg": True, "lpips_alex": True}


def load_runs(stems: list[str], method: str, folder: Path) -> tuple[list[int], dict]:
    """(seeds, {video: {region: {metric: [value per run]}}}) of ``method`` in the runs."""
    seeds, values = [], {}
    for stem in stems:
        doc = json.loads((folder / f"{stem}.json").read_text())
        seeds.append(int(doc["config"]["seed"]))
        for video, v in doc["videos"].items():
            entry = v["methods"].get(method)
            if entry is None:
                raise SystemExit(f"{stem}.json has no {method!r} run on {video}")
            for region in REGIONS:
                for metric, x in entry.get(region, {}).items():
                    if metric in LOWER_IS_BETTER:
                        values.setdefault(video, {}).setdefault(region, {}).setdefault(metric, []).append(x)
    return seeds, values


def compare_runs(before: dict, after: dict) -> dict:
    """{video: {region: {metric: {"before", "after": mean_std, "verdict", "gap_pct": mean_std}}}}."""
    out = {}
    for video, regions in after.items():
        for region, metrics in regions.items():
            for metric, a in metrics.items():
                b = before.get(video, {}).get(region, {}).get(metric)
                if b is None or len(b) != len(a):
                    continue
                verdict, gap = compare_paired(a, b, LOWER_IS_BETTER[metric])
                out.setdefault(video, {}).setdefault(region, {})[metric] = {
                    "before": mean_std(b),
                    "after": mean_std(a),
                    "verdict": verdict,
                    "gap_pct": gap,
                }
    return out


def title(doc: dict) -> str:
    """What is compared: one method before / after, or one method against another."""
    before = doc.get("before_method", doc["method"])
    if before == doc["method"]:
        return f"{doc['method']}, before / after"
    return f"{before} (before) / {doc['method']} (after)"


def markdown(doc: dict) -> str:
    lines = [
        f"# Real-video runs over seeds: {title(doc)}",
        "",
        header_line(doc),
        f"- before: {', '.join(doc['before'])} (seeds {doc['seeds']})",
        f"- after: {', '.join(doc['after'])} (seeds {doc['seeds']})",
        "- protocol, machine and load of each run: in its own result file",
        "",
        "LPIPS ×1000, mean ± std over the seeds. Gap: the per-seed relative change after vs before, "
        'mean ± std; a verdict other than "no difference" needs |mean| > std.',
        "",
        "| video | region | metric | before | after | gap % | verdict |",
        "|---|---|---|---:|---:|---:|---|",
    ]
    for video, regions in doc["comparison"].items():
        for region in REGIONS:
            for metric in ("lpips_vgg", "lpips_alex", "psnr", "ssim"):
                c = regions.get(region, {}).get(metric)
                if c is None:
                    continue
                scale, digits = (
                    (1000.0, 1) if metric.startswith("lpips") else (1.0, 4 if metric == "ssim" else 2)
                )
                gap = c["gap_pct"]
                lines.append(
                    f"| {video} | {region} | {metric} | {fmt(c['before'], scale, digits)} | "
                    f"{fmt(c['after'], scale, digits)} | "
                    f"{gap['mean']:+.1f} ± {gap['std']:.1f} | {c['verdict']} |"
                )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--method", default="eva", help="the method of the after runs (and of the before runs)")
    ap.add_argument("--before-method", help="the method of the before runs, when it is another")
    ap.add_argument("--before", nargs="+", required=True, help="result stems, one per seed")
    ap.add_argument("--after", nargs="+", required=True, help="result stems, one per seed")
    ap.add_argument("--name", required=True, help="result file stem")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    before_method = args.before_method or args.method
    seeds_b, before = load_runs(args.before, before_method, args.results)
    seeds_a, after = load_runs(args.after, args.method, args.results)
    if seeds_b != seeds_a:
        raise SystemExit(
            f"the runs' seeds differ: before {seeds_b}, after {seeds_a}; give them in the same order"
        )
    doc = {
        **run_header(),
        "method": args.method,
        "before_method": before_method,
        "before": args.before,
        "after": args.after,
        "seeds": seeds_a,
        "comparison": compare_runs(before, after),
    }
    write_result(args.results, args.name, doc, markdown(doc))
    print(markdown(doc))


if __name__ == "__main__":
    main()
