"""``wild_fits.log`` (one ``wild_fit.py`` line per calibration, labelled by the build's eye-corner
pixels, expressions and seed) as ``wild_fits.json``: ``python collect.py`` in this folder."""

import ast
import json
import re
from pathlib import Path

HERE = Path(__file__).resolve().parent
LINE = re.compile(
    r"eye_px=(\d+) samples=(\d+) seed=(\d+)( \(shipped\))?: expression ([\d.]+) mm, (\{.*\}) (\d+) s"
)

runs = []
for line in (HERE / "wild_fits.log").read_text().splitlines():
    m = LINE.fullmatch(line.strip())
    if m is None:
        raise SystemExit(f"unreadable line: {line}")
    px, samples, seed, shipped, mm, groups, seconds = m.groups()
    runs.append(
        {
            "eye_px": int(px),
            "samples": int(samples),
            "seed": int(seed),
            "shipped": shipped is not None,
            "expression_mm": float(mm),
            "groups_mm": ast.literal_eval(groups),
            "fit_seconds": int(seconds),
        }
    )
(HERE / "wild_fits.json").write_text(json.dumps({"runs": runs}, indent=1) + "\n")
print(len(runs), "runs")
