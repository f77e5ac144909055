"""How much the rendered eye range (5-95) of issue 39 rests on single frames: for each case of
stored ``bench expressions`` results, the range ratio as reported, its lowest and highest value
with any one test frame left out (and that frame), and a bootstrap interval over the frames
(``README.md``). Reads only committed result files; nothing is rendered or detected again.

    PYTHONPATH=. python bench/results/expressions/range_stability/range_stability.py

Writes ``range_stability.{json,md}`` beside this script.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, run_header, write_result
from eva_engine.eval.expression_fidelity import agreement

HERE = Path(__file__).resolve().parent
EXPRESSIONS = HERE.parent
SOURCES = {  # tag: (what it is, the result files whose cases are `<clip>_<tag>_s<seed>`)
    "base": ("the main issue 39 was filed on", ["calibration/expressions_base.json"]),
    "ce01": (
        "`fast` today",
        ["antialiased_default/expressions_ce01_g.json", "antialiased_default/expressions_ce01_s.json"],
    ),
    "fca": (
        "the default preset with the face close-ups (the job's options)",
        [
            "closeup_antialiased/expressions_closeup_antialiased_g.json",
            "closeup_antialiased/expressions_closeup_antialiased_s.json",
        ],
    ),
    "ctl": (
        "`fast` on its clip fitted again by this tree (the control of `../lid_calibration/`)",
        ["lid_calibration/expressions_ctl_g.json", "lid_calibration/expressions_ctl_s.json"],
    ),
    "lidcal": (
        "the same, fitted with the eye outlines calibrated for every action but the blinks",
        ["lid_calibration/expressions_lidcal_g.json", "lid_calibration/expressions_lidcal_s.json"],
    ),
    "lideye": (
        "the same, calibrated for the eye's own actions only",
        ["lid_calibration/expressions_lideye_g.json", "lid_calibration/expressions_lideye_s.json"],
    ),
    "lid6": (
        "the lids' six actions' colours (specks; not adopted)",
        ["lid_colours/expressions_lid6_g.json", "lid_colours/expressions_lid6_s.json"],
    ),
}
CLIPS = ("gesturing", "seated")
RESAMPLES = 2000
MEASURE = "eyes"


def ratio(target: np.ndarray, render: np.ndarray) -> float:
    return agreement(torch.from_numpy(target), torch.from_numpy(render)).range_ratio


def stability(case: dict) -> dict:
    """One case's eye range ratio: as reported, with each frame left out, and bootstrapped."""
    per = case["per_frame"]
    t = np.asarray(per["target"][MEASURE], dtype=np.float64)
    r = np.asarray(per["render"][MEASURE], dtype=np.float64)
    ok = np.isfinite(t) & np.isfinite(r)
    t, r, idx = t[ok], r[ok], np.asarray(per["index"])[ok]
    loo = np.array([ratio(np.delete(t, i), np.delete(r, i)) for i in range(t.size)])
    rng = np.random.default_rng(0)
    draws = rng.integers(0, t.size, size=(RESAMPLES, t.size))
    boot = np.array([ratio(t[d], r[d]) for d in draws])
    closed = np.argsort(t)[:6]  # the target's most closed frames, where the 5th percentile falls
    return {
        "frames": int(t.size),
        "range_ratio": ratio(t, r),
        "leave_one_out": {
            "min": float(loo.min()),
            "min_without": int(idx[loo.argmin()]),
            "max": float(loo.max()),
            "max_without": int(idx[loo.argmax()]),
        },
        "bootstrap_90": [float(np.quantile(boot, 0.05)), float(np.quantile(boot, 0.95))],
        "most_closed": [{"index": int(idx[i]), "target": float(t[i]), "render": float(r[i])} for i in closed],
    }


def cases() -> dict[str, dict]:
    out = {}
    for tag, (_, files) in SOURCES.items():
        for f in files:
            doc = json.loads((EXPRESSIONS / f).read_text())
            for name, case in doc["cases"].items():
                clip = name.split("_")[0]
                if clip in CLIPS and name.startswith(f"{clip}_{tag}_s"):
                    out[name] = {"tag": tag, "clip": clip, "source": f, **stability(case)}
    return out


def main() -> None:
    found = cases()
    doc = {**run_header(), "measure": MEASURE, "resamples": RESAMPLES, "cases": found}
    lines = ["# The rendered eye range: how much single frames move it", "", header_line(doc), ""]
    lines += [
        "Eye opening (MediaPipe on target and render, `bench expressions`), the render's 5-95 "
        "percentile range over the target's, per avatar. Leave one out: the lowest and highest ratio "
        "with any one test frame dropped (the frame in brackets). Bootstrap: the 5th-95th percentile "
        f"of the ratio over {RESAMPLES} resamples of the frames with replacement. Most closed: the "
        "target's five most closed frames, target → render.",
        "",
        "| avatar | what | case | frames | ratio | leave one out | bootstrap 90% "
        "| most closed, target → render |",
        "|---|---|---|---:|---:|---|---|---|",
    ]
    for name, c in found.items():
        lo = c["leave_one_out"]
        closed = ", ".join(f"{m['target']:.3f} → {m['render']:.3f}" for m in c["most_closed"][:5])
        lines.append(
            f"| {c['tag']} | {SOURCES[c['tag']][0]} | {name} | {c['frames']} | {c['range_ratio']:.2f} "
            f"| {lo['min']:.2f} ({lo['min_without']}) – {lo['max']:.2f} ({lo['max_without']}) "
            f"| {c['bootstrap_90'][0]:.2f} – {c['bootstrap_90'][1]:.2f} | {closed} |"
        )
    write_result(HERE, "range_stability", doc, lines, show=True)


if __name__ == "__main__":
    main()
