"""Synthetic benchmark generator speed (``eva_engine.synth.generate``), and the contact
sheet in docs/.

    .venv/bin/python -m bench synth [--sizes tiny bench] [--presets wild] [--seed 0]
                                    [--contact-sheet docs/synthetic_contact_sheet.png]

Times one generation per (preset, size) on CPU, model load excluded, into a temporary folder.
Writes ``bench/results/synth.json`` and ``synth.md``; with ``--contact-sheet`` also renders
the sheet (full frame, face, both hands for six frames) from the first ``bench`` dataset.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bench.machine import run_header, write_result
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.synth import PRESETS, SIZES, generate

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["tiny", "bench"], choices=list(SIZES))
    ap.add_argument("--presets", nargs="+", default=["wild"], choices=list(PRESETS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--contact-sheet", type=Path, default=None)
    args = ap.parse_args(argv)

    start = time.perf_counter()
    model = load_body_model("anny")
    load_s = time.perf_counter() - start
    rows = []
    sheet_done = False
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            for preset in args.presets:
                out = Path(tmp) / f"{preset}-{size}"
                stamps: list[float] = []
                t0 = time.perf_counter()
                generate(
                    preset,
                    size,
                    args.seed,
                    out,
                    model=model,
                    progress=lambda _, stamps=stamps: stamps.append(time.perf_counter()),
                )
                total = time.perf_counter() - t0
                n = len(stamps)
                per_frame = (stamps[-1] - stamps[0]) / max(n - 1, 1)
                setup = stamps[0] - t0 - per_frame  # motion, forward pass, texture bake
                rows.append(
                    {
                        "preset": preset,
                        "size": size,
                        "frames": n,
                        "px": SIZES[size].image_size,
                        "total_s": round(total, 2),
                        "setup_s": round(setup, 2),
                        "per_frame_ms": round(1e3 * per_frame, 1),
                    }
                )
                print(rows[-1], flush=True)
                if args.contact_sheet and size == "bench" and not sheet_done:
                    import cv2

                    from eva_engine.synth.contact_sheet import contact_sheet

                    ds = load_dataset(out)
                    picks = [0, 27, 55, 83, 111, 139]
                    img = contact_sheet(ds, picks, tile=256)
                    args.contact_sheet.parent.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(args.contact_sheet), img[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
                    sheet_done = True

    info = {
        **run_header(),
        "model_load_s": round(load_s, 2),
        "results": rows,
    }
    lines = [
        "# Synthetic benchmark generator",
        "",
        f"- date: {info['date']}",
        f"- command: `{info['command']}`",
        f"- machine: {info['machine']}",
        "- note: CPU shared with other jobs when recorded; timings are noisy.",
        "",
        "| preset | size | frames | px | total (s) | setup (s) | per frame (ms) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['size']} | {r['frames']} | {r['px']} | {r['total_s']} | "
            f"{r['setup_s']} | {r['per_frame_ms']} |"
        )
    lines += [
        "",
        "Per frame: render (mesh rasterizer, supersampled), region masks, PNG writing. Setup: "
        "motion, body-model forward, texture bake. Model load excluded "
        f"({info['model_load_s']} s).",
    ]
    write_result(RESULTS, "synth", info, lines)


if __name__ == "__main__":
    main()
