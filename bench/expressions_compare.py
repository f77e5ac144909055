"""Two groups of ``bench/expressions.py`` cases paired by seed: the render stage's mouth and eye
agreement and, with ``--closeup``, the close-ups as images.

    .venv/bin/python -m bench expressions_compare bench/results/expressions/closeups/closeup_gesturing.json \
        --before base --after face --name closeup_gesturing_paired

Cases are ``<group>_s<seed>``; a seed present in both groups is a pair. Correlations and range
ratios are compared as absolute gaps (after minus before), LPIPS and PSNR as relative ones (%);
either way a gap counts only when its mean exceeds the standard deviation of the per-seed gaps
(``stats``), otherwise it is "no difference". Writes ``<out>/<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result
from bench.stats import compare_paired, fmt, mean_std
from eva_engine.eval.expression_fidelity import agreement

RESULTS = Path(__file__).resolve().parent / "results"
# (key, label, higher is better, relative gap)
MEASURES = (
    ("mouth_r", "render: mouth r", True, False),
    ("mouth_range", "render: mouth range over the target's", True, False),
    ("eyes_r", "render: eyes r", True, False),
    ("eyes_range", "render: eyes range over the target's", True, False),
    ("mouth_full_range", "render: mouth full range (max - min) over the target's", True, False),
    ("eyes_full_range", "render: eyes full range (max - min) over the target's", True, False),
    ("psnr", "close-up PSNR", True, True),
    ("lpips_vgg", "close-up LPIPS-VGG ×1000", False, True),
)


def values(case: dict) -> dict[str, float]:
    """The compared measures of one case (missing ones absent)."""
    out = {}
    render = case["stages"].get("render")
    if render is not None:
        for m in ("mouth", "eyes"):
            out[f"{m}_r"] = render[m]["r"]
            out[f"{m}_range"] = render[m]["range_ratio"]
            out[f"{m}_full_range"] = full_range_ratio(case, m)
    images = case.get("closeup_images")
    if images is not None:
        out["psnr"] = images["psnr"]
        out["lpips_vgg"] = 1000.0 * images["lpips_vgg"]
    return out


def full_range_ratio(case: dict, measure: str) -> float:
    """The render's full range over the target's (``Agreement.full_range_ratio``), recomputed from
    the case's per-frame openings for results written before that field."""
    got = case["stages"]["render"][measure].get("full_range_ratio")
    if got is not None:
        return got
    frames = case["per_frame"]
    target, render = (torch.tensor(frames[k][measure], dtype=torch.float64) for k in ("target", "render"))
    return agreement(target, render).full_range_ratio


def by_seed(cases: dict, group: str) -> dict[str, dict[str, float]]:
    return {
        label.rpartition("_s")[2]: values(case)
        for label, case in cases.items()
        if label.rpartition("_s")[0] == group and label.rpartition("_s")[2].isdigit()
    }


def absolute(after: list[float], before: list[float], higher_is_better: bool) -> tuple[str, dict]:
    """The paired rule on absolute gaps (after - before)."""
    gaps = mean_std([a - b for a, b in zip(after, before, strict=True)])
    if len(after) < 2:
        return "too few seeds", gaps
    if abs(gaps["mean"]) <= gaps["std"] or math.isnan(gaps["mean"]):
        return "no difference", gaps
    return ("better" if (gaps["mean"] > 0) == higher_is_better else "worse"), gaps


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", type=Path, nargs="+", help="bench/expressions.py JSON files")
    ap.add_argument("--before", required=True, help="case group (label without _s<seed>)")
    ap.add_argument("--after", required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    cases: dict = {}
    for path in args.results:
        cases.update(json.loads(path.read_text())["cases"])
    before, after = by_seed(cases, args.before), by_seed(cases, args.after)
    seeds = sorted(set(before) & set(after), key=int)
    if not seeds:
        raise SystemExit(f"no seed has both a {args.before!r} and an {args.after!r} case")
    rows = []
    for key, label, higher, relative in MEASURES:
        pairs = [(after[s][key], before[s][key]) for s in seeds if key in after[s] and key in before[s]]
        if not pairs:
            continue
        a, b = [p[0] for p in pairs], [p[1] for p in pairs]
        if relative:
            verdict, gaps = compare_paired(a, b, lower_is_better=not higher)
        else:
            verdict, gaps = absolute(a, b, higher)
        rows.append(
            {
                "measure": key,
                "label": label,
                "seeds": len(pairs),
                "before": mean_std(b),
                "after": mean_std(a),
                "gap": gaps,
                "gap_unit": "%" if relative else "absolute",
                "verdict": verdict,
            }
        )
    doc = {
        **run_header(),
        "sources": [str(p) for p in args.results],
        "before": args.before,
        "after": args.after,
    }
    doc["seeds"] = seeds
    doc["rows"] = rows
    lines = [
        f"# {args.after} against {args.before}, paired by seed",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- sources: {', '.join(f'`{Path(p).name}`' for p in args.results)}; seeds {', '.join(seeds)}",
        "",
        "Gap: after minus before per seed, mean ± std (% for PSNR and LPIPS, absolute otherwise); "
        "better or worse only when the mean gap exceeds the gaps' standard deviation.",
        "",
        f"| measure | seeds | {args.before} | {args.after} | gap | verdict |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        unit = " %" if r["gap_unit"] == "%" else ""
        lines.append(
            f"| {r['label']} | {r['seeds']} | {fmt(r['before'])} | {fmt(r['after'])} | "
            f"{fmt(r['gap'])}{unit} | {r['verdict']} |"
        )
    write_result(args.out, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
