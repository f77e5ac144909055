"""Synthetic `wild` (150 frames, `bench align`'s clip) detected once, then fitted by the product's
fit under the shipped calibration and under each variant of ``variant.py`` (``README.md``).

    PYTHONPATH=. python bench/results/expressions/lid_calibration/wild.py \
        shipped every=$TMPDIR/lidcal/every.json eye=$TMPDIR/lidcal/eye.json

Writes ``wild.{json,md}`` beside this script.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, run_header, write_result

HERE = Path(__file__).resolve().parent


def main(*variants: str) -> None:
    import eva_engine.align.objective as objective
    from eva_engine.align import detect_frames
    from eva_engine.align.clip import fit_clip
    from eva_engine.align.evaluate import expression_error, expression_error_by_group
    from eva_engine.align.face_calibration import DetectorCalibration
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset
    from eva_engine.paths import data_dir
    from eva_engine.synth import generate

    torch.set_num_threads(1)
    model = load_body_model("anny")
    dataset = data_dir() / "synthetic" / "wild-bench-seed0"
    if not (dataset / "meta.json").exists():
        generate("wild", "bench", 0, dataset, model=model)
    ds = load_dataset(dataset)
    order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:150]
    K, view = ds.K[order], ds.viewmat[order]
    images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    targets = detect_frames(iter(images)).targets(K, view)
    truth = ds.gt_params.map(lambda t: t[order])
    shipped = objective.load_calibration
    runs = {}
    for v in variants:
        label, _, path = v.partition("=")
        if path:
            cal = DetectorCalibration.from_json(json.loads(Path(path).read_text()))
            objective.load_calibration = lambda *a, _cal=cal, **k: _cal
        else:
            objective.load_calibration = shipped
        started = time.perf_counter()
        fit = fit_clip(model, targets, ds.timestamps[order])
        runs[label] = {
            "expression_mm": expression_error(model, fit.params, truth),
            "by_group": expression_error_by_group(model, fit.params, truth),
            "fit_s": time.perf_counter() - started,
        }
        print(label, runs[label], flush=True)
    doc = {**run_header(), "dataset": str(dataset), "frames": len(order), "runs": runs}
    lines = ["# Synthetic `wild`: the expression error under each calibration", "", header_line(doc), ""]
    lines += [
        "The product's fit of the same detections; expression error against the truth, mm (the neutral "
        "face's in brackets).",
        "",
        "| calibration | expression | jaw | lips | lids | brows | fit (s) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, r in runs.items():
        g = r["by_group"]
        cells = " | ".join(f"{g[k]:.2f} ({g[k + '_neutral']:.2f})" for k in ("jaw", "lips", "lids", "brows"))
        lines.append(f"| {label} | {r['expression_mm']:.2f} | {cells} | {r['fit_s']:.0f} |")
    write_result(HERE, "wild", doc, lines, show=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
