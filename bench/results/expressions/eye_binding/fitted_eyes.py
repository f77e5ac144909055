"""How wide and how closed each upper-body clip's fit holds the eyes (and the jaw): their actions' quantiles
over every frame of each dataset, and the frames at the upper bound (``README.md``).

    PYTHONPATH=. python bench/results/expressions/eye_binding/fitted_eyes.py \
        data/s40/gesturing data/s40/seated

Writes ``fitted_eyes.{json,md}`` beside this script.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result

HERE = Path(__file__).resolve().parent
ACTIONS = (
    "eyeBlinkLeft",
    "eyeBlinkRight",
    "eyeWideLeft",
    "eyeWideRight",
    "eyeSquintLeft",
    "eyeSquintRight",
    "jawOpen",
)
QUANTILES = (0.5, 0.9, 0.99, 1.0)
AT_BOUND = 0.99


def summary(values: torch.Tensor) -> dict:
    """[F] one action's coefficients -> their quantiles and the frames at the upper bound."""
    q = torch.quantile(values.double(), torch.tensor(QUANTILES, dtype=torch.float64)).tolist()
    at_bound = int((values >= AT_BOUND).sum())
    return {"quantiles": dict(zip(map(str, QUANTILES), q, strict=True)), "at_bound": at_bound}


def main(*datasets: str) -> None:
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset

    names = list(load_body_model("anny").expression_names)
    clips = {}
    for path in datasets:
        expression = load_dataset(path).params.expression
        clips[Path(path).name] = {
            "frames": int(expression.shape[0]),
            **{action: summary(expression[:, names.index(action)]) for action in ACTIONS},
        }
    doc = {**run_header(), "datasets": list(datasets), "at_bound": AT_BOUND, "clips": clips}
    lines = ["# The fitted eye actions (and the jaw) of the upper-body clips", "", header_line(doc), ""]
    lines += [
        "| clip | action | median | p90 | p99 | max | frames at >= 0.99 |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for clip, c in clips.items():
        for action in ACTIONS:
            q = c[action]["quantiles"]
            cells = " | ".join(f"{q[str(k)]:.2f}" for k in QUANTILES)
            lines.append(f"| {clip} | {action} | {cells} | {c[action]['at_bound']} of {c['frames']} |")
    write_result(HERE, "fitted_eyes", doc, lines)


if __name__ == "__main__":
    main(*sys.argv[1:])
