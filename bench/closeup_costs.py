"""What the face close-ups cost: cutting them (``add_face_crops``, a decoding pass at the video's
size) and training with them (the ``avatar.json`` times of avatars trained with and without).

    D=data/face_default/gesturing-nosmooth
    .venv/bin/python -m bench closeup_costs --cut $D/dataset <video> \
        --avatars $D/avatar-product-s0 $D/avatar-face-s0 --name closeup_costs --out <folder>

``--cut`` cuts the dataset's close-ups again in place (the same ones: the cut is deterministic).
Training times are what each avatar recorded; how many runs shared the cores then is not known
here, so compare avatars trained side by side.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from bench.machine import header_line, run_header, write_result

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: list[str] | None = None) -> None:
    from eva_engine.align.preprocess import PreprocessConfig, add_face_crops

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cut", nargs=2, action="append", default=[], metavar=("DATASET", "VIDEO"))
    ap.add_argument("--avatars", nargs="*", type=Path, default=[])
    ap.add_argument("--name", default="closeup_costs")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    doc = {**run_header(), "cuts": [], "avatars": []}
    for dataset, video in args.cut:
        started = time.perf_counter()
        crops = add_face_crops(dataset, video, PreprocessConfig())
        seconds = time.perf_counter() - started
        frames = len(crops.frames) if crops is not None else 0
        size = crops.size if crops is not None else None
        doc["cuts"].append(
            {
                "dataset": dataset,
                "video": Path(video).name,
                "frames": frames,
                "size": size,
                "seconds": seconds,
            }
        )
    for avatar in args.avatars:
        meta = json.loads((avatar / "avatar.json").read_text())
        face = (meta.get("train_config") or {}).get("face_view") or {}
        doc["avatars"].append(
            {
                "avatar": str(avatar),
                "face_view_weight": face.get("weight", 0.0),
                "train_seconds": meta["train_seconds"],
                "timings": meta.get("timings", {}),
            }
        )
    lines = ["# Face close-ups: what they cost", "", header_line(doc), f"- machine: {doc['machine']}", ""]
    if doc["cuts"]:
        lines += ["| dataset | video | close-ups | size (px) | cut (s) |", "|---|---|---:|---:|---:|"]
        for c in doc["cuts"]:
            lines.append(
                f"| `{c['dataset']}` | {c['video']} | {c['frames']} | {c['size']} | {c['seconds']:.1f} |"
            )
        lines.append("")
    if doc["avatars"]:
        lines += [
            "Training, as each `avatar.json` recorded it (s):",
            "",
            "| avatar | face_view.weight | train | close-up render and loss | backward |",
            "|---|---:|---:|---:|---:|",
        ]
        for a in doc["avatars"]:
            t = a["timings"]
            lines.append(
                f"| `{a['avatar']}` | {a['face_view_weight']:g} | {a['train_seconds']:.1f} | "
                f"{t.get('face_view', 0.0):.1f} | {t.get('backward', float('nan')):.1f} |"
            )
    write_result(args.out, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
