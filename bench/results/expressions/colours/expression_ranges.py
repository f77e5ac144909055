"""The revealing actions' coefficients in each split of the datasets given (mean, largest, and
how many frames above 0.3), written as JSON:

    python bench/results/expressions/colours/expression_ranges.py OUT.json DATASET...
"""

import json
import sys

from safetensors.torch import load_file

from eva_engine.body import load_body_model

ACTIONS = ("eyeBlinkLeft", "eyeBlinkRight", "jawOpen")
names = list(load_body_model("anny").expression_names)
out = {}
for root in sys.argv[2:]:
    params = load_file(f"{root}/params.safetensors")["expression"]
    with open(f"{root}/splits.json") as f:
        splits = {k: v for k, v in json.load(f).items() if v}
    out[root] = {
        split: {
            a: {
                "mean": round(float(params[rows, names.index(a)].mean()), 3),
                "max": round(float(params[rows, names.index(a)].max()), 3),
                "frames_above_0.3": int((params[rows, names.index(a)] > 0.3).sum()),
                "frames": len(rows),
            }
            for a in ACTIONS
        }
        for split, rows in splits.items()
    }
with open(sys.argv[1], "w") as f:
    json.dump(out, f, indent=1)
