"""The fit with the expression kept in its range (``FitConfig.bounded_expression``, L-BFGS-B) and
without (torch's L-BFGS, the range penalty and a final clamp), on the stored detections of the two
upper-body clips and on synthetic ``wild``'s 150 frames, each fitted in full (``fit_clip``):

    PYTHONPATH=. python bench/results/expressions/bounded/fits.py fit <bounded|penalty> <clip>
    PYTHONPATH=. python bench/results/expressions/bounded/fits.py collect

``<clip>``: ``gesturing`` or ``seated`` (``data/face39/<clip>-noeyes``, the datasets of
``../colour_spread/``) or ``wild`` (``data/synthetic/wild-bench-seed0``, MediaPipe Holistic's
detections cached in ``$TMPDIR/wild_detections.pkl``, the fit of ``../calibration/draws/wild_fit.py``:
``hand_depth_scale`` 1). ``fit`` appends one JSON line to ``fits.jsonl`` (one thread); ``collect``
writes ``fits.{json,md}``. The clips: the fitted eye and mouth openings
(``eval.expression_fidelity.openings``) against the stored detections over every frame (Pearson r,
the 5-95 percentile range's width over the detections'); ``wild``: the expression error (mm) against
the truth, per facial-action group too."""

from __future__ import annotations

import dataclasses
import json
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.machine import run_header, write_result

HERE = Path(__file__).resolve().parent
LOG = HERE / "fits.jsonl"
CLIPS = {"gesturing": "face39/gesturing-noeyes", "seated": "face39/seated-noeyes"}


def _agreement(detected: torch.Tensor, fitted: torch.Tensor) -> dict:
    ok = torch.isfinite(detected) & torch.isfinite(fitted)
    d, f = detected[ok].double(), fitted[ok].double()
    q = torch.tensor([0.05, 0.95], dtype=torch.float64)
    (d0, d1), (f0, f1) = torch.quantile(d, q).tolist(), torch.quantile(f, q).tolist()
    return {"r": float(torch.corrcoef(torch.stack([d, f]))[0, 1]), "range_ratio": (f1 - f0) / (d1 - d0)}


def fit(variant: str, clip: str) -> dict:
    from bench.expressions import stored_targets
    from eva_engine.align.clip import fit_clip
    from eva_engine.align.evaluate import expression_error, expression_error_by_group, mpjpe
    from eva_engine.align.face_mesh import load_correspondence
    from eva_engine.align.stages import FitConfig
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset
    from eva_engine.eval.expression_fidelity import fitted_landmarks, openings
    from eva_engine.paths import data_dir

    torch.set_num_threads(1)
    model = load_body_model("anny")
    config = FitConfig(bounded_expression=variant == "bounded")
    row = {"variant": variant, "clip": clip}
    if clip == "wild":
        ds = load_dataset(data_dir() / "synthetic" / "wild-bench-seed0")
        order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:150]
        K, view = ds.K[order], ds.viewmat[order]
        cache = Path(tempfile.gettempdir()) / "wild_detections.pkl"
        if cache.exists():
            targets = pickle.loads(cache.read_bytes())
        else:
            from eva_engine.align import detect_frames

            images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
            targets = detect_frames(iter(images)).targets(K, view)
            cache.write_bytes(pickle.dumps(targets))
        started = time.perf_counter()
        params = fit_clip(
            model, targets, ds.timestamps[order], dataclasses.replace(config, hand_depth_scale=1.0)
        )
        row["seconds"] = time.perf_counter() - started
        truth = ds.gt_params.map(lambda t: t[order])
        row["expression_mm"] = expression_error(model, params.params, truth)
        row["groups_mm"] = expression_error_by_group(model, params.params, truth)
        row["mpjpe_mm"] = mpjpe(model, params.params, truth, ds.gt_keypoints[order][..., 2] > 0)
        return row
    ds = load_dataset(data_dir() / CLIPS[clip])
    started = time.perf_counter()
    params = fit_clip(model, stored_targets(ds), ds.timestamps, config).params
    row["seconds"] = time.perf_counter() - started
    reg, ids = load_correspondence(model).regressor(model)
    detected = openings(ds.keypoint_extras["face_mesh"])
    fitted = openings(fitted_landmarks(model, params, reg, ids, ds.K, ds.viewmat))
    row.update({m: _agreement(detected[m], fitted[m]) for m in ("eyes", "mouth")})
    return row


def collect() -> None:
    rows = [json.loads(line) for line in LOG.read_text().splitlines() if line.strip()]
    doc = {**run_header(), "runs": rows}
    lines = [
        "# The expression kept in its range: the fit on both upper-body clips and synthetic `wild`",
        "",
        f"- date: {doc['date']}; machine: {doc['machine']}",
        "- commands: `PYTHONPATH=. python bench/results/expressions/bounded/fits.py fit <variant> <clip>` "
        "per row (one thread; see the README for what shared the cores), then `... fits.py collect`",
        "",
        "| variant | clip | eyes r | eyes range / detections' | mouth r | mouth range / detections' "
        "| expression, mm | jaw / lips / lids / brows, mm | body in view / hands, mm | seconds |",
        "|---|---|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    for r in rows:
        if r["clip"] == "wild":
            g = r["groups_mm"]
            cells = [
                "",
                "",
                "",
                "",
                f"{r['expression_mm']:.2f}",
                " / ".join(f"{g[k]:.2f}" for k in ("jaw", "lips", "lids", "brows")),
                f"{r['mpjpe_mm']['body_in_view']:.1f} / {r['mpjpe_mm']['hands']:.1f}",
            ]
        else:
            cells = [
                f"{r['eyes']['r']:.3f}",
                f"{r['eyes']['range_ratio']:.2f}",
                f"{r['mouth']['r']:.3f}",
                f"{r['mouth']['range_ratio']:.2f}",
                "",
                "",
                "",
            ]
        lines.append(f"| {r['variant']} | {r['clip']} | " + " | ".join(cells) + f" | {r['seconds']:.0f} |")
    write_result(HERE, "fits", doc, lines)


if __name__ == "__main__":
    if sys.argv[1] == "collect":
        collect()
    else:
        row = fit(sys.argv[2], sys.argv[3])
        with open(LOG, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
