"""How far MediaPipe's 2D keypoints sit from the true ones on the hard clips (issue 41): per joint
group, the share of frames with a confident detection (confidence >= 0.5) and, over those, the
error against the true projection (px, median). The fit's 2D term pulls toward these points.

    .venv/bin/python bench/results/hard_inputs_refit/detection_error.py --cases closeup clean \\
        --seed 0 --work <scratch> --out bench/results/hard_inputs_refit
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from bench.closeup_levers import VARIANTS, preprocess_config  # noqa: E402
from bench.fit_levers import JOINT_GROUPS, clip_and_detections, projected_keypoints  # noqa: E402
from bench.machine import header_line, run_header, write_result  # noqa: E402


def main() -> None:
    from eva_engine.align.camera import guess_camera
    from eva_engine.body import KEYPOINT_NAMES, load_body_model
    from eva_engine.synth.hard import hard_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", nargs="+", default=["closeup", "clean"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("anny")
    groups = {
        **JOINT_GROUPS,
        "fingers": (
            "left_hand_index_finger_tip",
            "right_hand_index_finger_tip",
            "left_hand_thumb_tip",
            "right_hand_thumb_tip",
        ),
    }
    groups = {g: [n for n in names if n in KEYPOINT_NAMES] for g, names in groups.items()}
    doc = {**run_header(), "seed": args.seed, "cases": {}}
    for case in args.cases:
        hv, clip, det = clip_and_detections(case, args.seed, args.work, model)
        h, w = clip.frames.shape[1:3]
        K, viewmat = guess_camera(w, h, preprocess_config(VARIANTS["baseline"]).fov_y_deg)
        kp = torch.as_tensor(det.targets(K, viewmat).keypoints, dtype=torch.float32)  # [F, K, 3]
        scene = hard_scene(case, args.seed, frames=len(hv.times), size=w, model=model)
        truth = projected_keypoints(model, scene.sharp_params, scene.viewmat, scene.K)
        rows = {}
        for group, names in groups.items():
            idx = [KEYPOINT_NAMES.index(n) for n in names]
            sure = torch.isfinite(kp[:, idx, :2]).all(-1) & (kp[:, idx, 2] >= 0.5)
            err = (kp[:, idx, :2] - truth[:, idx]).norm(dim=-1)[sure]
            rows[group] = {
                "found": float(sure.float().mean()),
                "median_px": float(err.median()) if err.numel() else None,
            }
        doc["cases"][case] = rows
    lines = [
        "# MediaPipe's 2D keypoints against the truth on the hard clips",
        "",
        header_line(doc),
        "",
        "Per joint group: the share of (frame, point) pairs detected with confidence >= 0.5, and over "
        "those the median distance to the true projection (px, 512 px frames).",
        "",
        "| case | " + " | ".join(f"{g}: found, px" for g in groups) + " |",
        "|---|" + "---|" * len(groups),
    ]
    for case, rows in doc["cases"].items():
        cells = [
            f"{r['found']:.0%}, {r['median_px']:.1f}"
            if r["median_px"] is not None
            else f"{r['found']:.0%}, –"
            for r in rows.values()
        ]
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    write_result(args.out, f"detection_error_s{args.seed}", doc, lines, show=True)


if __name__ == "__main__":
    main()
