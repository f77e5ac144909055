"""The lid actions a fit gives chosen frames: eyeBlink, eyeSquint, eyeWide, eyeLookUp and
eyeLookDown, left / right, per dataset (``README.md``).

    PYTHONPATH=. python bench/results/expressions/range_stability/fitted_lids.py \
        --name fitted_lids data/s40/gesturing ... --frames 67 35 123 199 235 159

Writes ``<name>.{json,md}`` beside this script.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench.machine import header_line, run_header, write_result

HERE = Path(__file__).resolve().parent
ACTIONS = ("eyeBlink", "eyeSquint", "eyeWide", "eyeLookUp", "eyeLookDown")


def lids(dataset: str, frames: list[int]) -> dict:
    """{frame: {action: [left, right]}} of one dataset's fit."""
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset

    names = list(load_body_model("anny").expression_names)
    expression = load_dataset(dataset).params.expression
    return {
        str(f): {
            a: [round(float(expression[f, names.index(a + side)]), 3) for side in ("Left", "Right")]
            for a in ACTIONS
        }
        for f in frames
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--frames", type=int, nargs="+", required=True)
    ap.add_argument("--name", default="fitted_lids")
    args = ap.parse_args(argv)
    found = {d: lids(d, args.frames) for d in args.datasets}
    doc = {**run_header(), "frames": args.frames, "datasets": found}
    lines = ["# The lid actions the fit gives chosen frames", "", header_line(doc), ""]
    lines += ["Each action left / right.", ""]
    lines += ["| dataset | frame | " + " | ".join(ACTIONS) + " |", "|---|---:|" + "---|" * len(ACTIONS)]
    for d, frames in found.items():
        for f, acts in frames.items():
            lines.append(
                f"| {d} | {f} | " + " | ".join(f"{a[0]:.2f} / {a[1]:.2f}" for a in acts.values()) + " |"
            )
    write_result(HERE, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
