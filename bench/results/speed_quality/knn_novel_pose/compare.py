"""The exact initial scales (b9b9fe3) against ``torch.cdist``'s (493cb9d) on the novel-pose
benchmark, paired by seed: ``python compare.py FOLDER`` with ``knn_{base,new}_s{0,1,2}.json`` in
FOLDER (``bench/novel_pose.py`` runs of the default row) prints the Markdown table of ``README.md``.
LPIPS-VGG is held out (the default trains on LPIPS-Alex)."""

import json
import sys
from pathlib import Path

from bench.stats import compare_paired, mean_std

ROW = "thin_blink_colours"
SPLITS = ("near", "far", "view", "far_view")
REGIONS = ("full", "hand", "face", "arm")
folder = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).parent)


def runs(side: str) -> list[dict]:
    found = [json.loads((folder / f"knn_{side}_s{s}.json").read_text()) for s in (0, 1, 2)]
    return [doc["methods"][ROW]["runs"][0] for doc in found]


base, new = runs("base"), runs("new")
assert [r["seed"] for r in base] == [r["seed"] for r in new] == [0, 1, 2]
print("| split | region | measure | cdist (base) | k-d tree | gap, per seed |")
print("|---|---|---|---:|---:|---|")
for split in SPLITS:
    for region in REGIONS:
        for key, lower in (("lpips_vgg", True), ("psnr", False)):
            a = [r["splits"][split][region][key] for r in new]
            b = [r["splits"][split][region][key] for r in base]
            verdict, gap = compare_paired(a, b, lower_is_better=lower)
            scale = 1000.0 if key == "lpips_vgg" else 1.0
            cells = [mean_std([scale * v for v in vs]) for vs in (b, a)]
            name = "LPIPS-VGG ×1000" if key == "lpips_vgg" else "PSNR"
            print(
                f"| {split} | {region} | {name} | {cells[0]['mean']:.1f} ± {cells[0]['std']:.1f} "
                f"| {cells[1]['mean']:.1f} ± {cells[1]['std']:.1f} "
                f"| {gap['mean']:+.1f} ± {gap['std']:.1f}%, {verdict} |"
            )
    for key in ("debris", "holes"):
        a, b = [r["splits"][split][key] for r in new], [r["splits"][split][key] for r in base]
        verdict, gap = compare_paired(a, b, lower_is_better=True)
        print(
            f"| {split} | image | {key}, % of the image | {100 * mean_std(b)['mean']:.3f} "
            f"| {100 * mean_std(a)['mean']:.3f} | {gap['mean']:+.1f} ± {gap['std']:.1f}%, {verdict} |"
        )
