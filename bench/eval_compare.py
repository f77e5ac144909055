"""Two sets of ``eva eval --json`` results paired by position (the same dataset and seed, one
setting changed), per region and metric: mean ± std of each, the per-seed relative gap and the
verdict of ``stats.compare_paired`` (better / worse only when the mean gap exceeds its standard
deviation, otherwise "no difference").

    .venv/bin/python -m bench eval_compare --before a_s0.json a_s1.json a_s2.json \\
        --after b_s0.json b_s1.json b_s2.json --name thin_face --out bench/results/...

Writes ``<name>.json`` and ``<name>.md`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench.machine import header_line, run_header, write_result
from bench.stats import compare_paired, fmt, mean_std

LOWER_IS_BETTER = {"psnr": False, "ssim": False, "lpips_vgg": True, "lpips_alex": True}
SCALE = {"psnr": 1.0, "ssim": 1.0, "lpips_vgg": 1000.0, "lpips_alex": 1000.0}


def regions(path: Path) -> dict[str, dict[str, float | None]]:
    return json.loads(path.read_text())["regions"]


def compare_runs(before: list[Path], after: list[Path]) -> list[dict]:
    """One row per region and metric found in every run."""
    if len(before) != len(after):
        raise SystemExit("--before and --after need the same number of runs (paired by position)")
    a_runs, b_runs = [regions(p) for p in before], [regions(p) for p in after]
    rows = []
    for region in a_runs[0]:
        for metric, lower in LOWER_IS_BETTER.items():
            a = [r.get(region, {}).get(metric) for r in a_runs]
            b = [r.get(region, {}).get(metric) for r in b_runs]
            if any(v is None for v in (*a, *b)):
                continue
            verdict, gap = compare_paired(b, a, lower)
            rows.append(
                {
                    "region": region,
                    "metric": metric,
                    "before": mean_std(a),
                    "after": mean_std(b),
                    "gap_percent": gap,
                    "verdict": verdict,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", type=Path, nargs="+", required=True)
    ap.add_argument("--after", type=Path, nargs="+", required=True)
    ap.add_argument("--before-label", default="before")
    ap.add_argument("--after-label", default="after")
    ap.add_argument("--name", required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = compare_runs(args.before, args.after)
    doc = {
        **run_header(),
        "before": [str(p) for p in args.before],
        "after": [str(p) for p in args.after],
        "rows": rows,
    }
    lines = [
        f"# {args.after_label} against {args.before_label}, paired",
        "",
        header_line(doc),
        f"- {len(args.before)} runs each, paired by position (same dataset, same seed); `eva eval` on the "
        "held-out frames; LPIPS ×1000 (LPIPS-VGG is held out: no method trains on it)",
        "",
        f"| region | metric | {args.before_label} | {args.after_label} | gap (%) | verdict |",
        "|---|---|---:|---:|---:|---|",
    ]
    for r in rows:
        scale, digits = SCALE[r["metric"]], 4 if r["metric"] == "ssim" else 2
        lines.append(
            f"| {r['region']} | {r['metric']} | {fmt(r['before'], scale, digits)} | "
            f"{fmt(r['after'], scale, digits)} | {fmt(r['gap_percent'], 1.0, 1)} | {r['verdict']} |"
        )
    write_result(args.out, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
