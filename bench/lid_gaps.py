"""The lid gaps in pixels: how far the fitted face's lids are from the detected ones, on the
clip's most closed frames and its median one, and how the gap moves with the blink.

    .venv/bin/python -m bench lid_gaps data/face_default/gesturing-nosmooth/dataset \
        --name lid_gaps --out bench/results/expressions/closeups

For each picked frame: the detected vertical gap of each lid pair the fit's opening term uses
(``OPENING_PAIRS``, upper minus lower landmark, frame pixels: negative when open), then the
fitted face's gap minus the detected one at the fitted blink and with both eyeBlink
coefficients set to 0 ... 1 (the frame's other parameters as fitted).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result

RESULTS = Path(__file__).resolve().parent / "results"
BLINKS = (0.0, 0.25, 0.5, 0.6, 0.75, 1.0)


def main(argv: list[str] | None = None) -> None:
    from eva_engine.align.face_mesh import OPENING_PAIRS, load_correspondence
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset
    from eva_engine.eval.expression_fidelity import fitted_landmarks, openings

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--closed", type=int, default=3, help="how many of the most closed frames")
    ap.add_argument("--name", default="lid_gaps")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ds = load_dataset(args.dataset)
    model = load_body_model(ds.meta.body_model or "anny")
    reg, ids = load_correspondence(model).regressor(model)
    det = ds.keypoint_extras["face_mesh"]
    eyes = openings(det)["eyes"]
    order = torch.argsort(eyes).tolist()
    frames = order[: args.closed] + [order[len(order) // 2]]
    names = model.expression_names
    blink = [names.index("eyeBlinkLeft"), names.index("eyeBlinkRight")]
    pairs = OPENING_PAIRS[:6]
    doc = {**run_header(), "dataset": str(args.dataset), "pairs": [list(p) for p in pairs], "frames": []}
    for f in frames:
        p = dataclasses.replace(
            ds.params,
            **{
                k: getattr(ds.params, k)[f : f + 1]
                for k in ("root_orient", "transl", "joints", "expression", "shape")
            },
        )
        detected = [float(det[f, a, 1] - det[f, b, 1]) for a, b in pairs]
        rows = {}
        for value in (None, *BLINKS):
            q = dataclasses.replace(p, expression=p.expression.clone())
            if value is not None:
                q.expression[0, blink] = value
            fl = fitted_landmarks(model, q, reg, ids, ds.K[f : f + 1], ds.viewmat[f : f + 1])
            rows["fitted" if value is None else f"{value:g}"] = [
                float(fl[0, a, 1] - fl[0, b, 1]) - d for (a, b), d in zip(pairs, detected, strict=True)
            ]
        doc["frames"].append(
            {
                "frame": f,
                "eye_opening": float(eyes[f]),
                "fitted_blink": [float(p.expression[0, i]) for i in blink],
                "detected_px": detected,
                "model_minus_detected_px": rows,
            }
        )
    head = " | ".join(f"{a}-{b}" for a, b in pairs)
    lines = [
        "# Lid gaps in pixels: fitted against detected",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- dataset: `{args.dataset}` ({ds.meta.image_size[1]}x{ds.meta.image_size[0]} px frames)",
        "",
        "Per frame (the most closed by the detected eye opening, then the median one): the detected "
        "vertical gap of each lid pair (upper minus lower landmark, px; negative: open), then the "
        "fitted face's gap minus the detected one at the fitted blink and at each blink value "
        "(both eyeBlink coefficients; the rest as fitted). Pairs: right eye 160-144, 159-145, "
        "158-153; left eye 385-380, 386-374, 387-373.",
        "",
    ]
    for e in doc["frames"]:
        lines += [
            f"## Frame {e['frame']}: eye opening {e['eye_opening']:.4f}, fitted blink "
            f"{e['fitted_blink'][0]:.2f} / {e['fitted_blink'][1]:.2f}",
            "",
            f"| | {head} |",
            "|---|" + "---:|" * len(pairs),
            "| detected gap | " + " | ".join(f"{v:+.2f}" for v in e["detected_px"]) + " |",
        ]
        for key, vals in e["model_minus_detected_px"].items():
            label = "fitted − detected" if key == "fitted" else f"blink {key} − detected"
            lines.append(f"| {label} | " + " | ".join(f"{v:+.2f}" for v in vals) + " |")
        lines.append("")
    write_result(args.out, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
