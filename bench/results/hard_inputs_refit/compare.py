"""The bounded (σ ≤ 10 cm) seed-0 hard-input runs of ``../hard_inputs.json`` (before the face
stage's change, stop 64) against the same runs at 1dc9f4c: ``python compare.py <work folder of
python -m bench hard_inputs --seeds 0 --max-scale-cm 10 --work <folder>>``; prints Markdown."""

import json
import sys
from pathlib import Path

from eva_engine.eval.quality import VerdictRules

old = json.loads((Path(__file__).parent.parent / "hard_inputs.json").read_text())["results"]
work = Path(sys.argv[1])
rules = VerdictRules()
print("| case | truth LPIPS-VGG ×1000, before → now | truth PSNR | report LPIPS | verdict | largest σ (cm) |")
print("|---|---|---|---|---|---|")
for case in ("clean", "closeup", "cropped", "blur", "dark", "second_person"):
    bounded = [r for r in old if r["case"] == case and r["seed"] == 0 and r.get("max_scale_cm") == 10]
    now = json.loads((work / f"{case}_cap10_s0" / "result.json").read_text())
    b = bounded[0] if bounded else {}
    bt, nt = b.get("truth", {}), now["truth"]
    bq, nq = b.get("quality", {}), now["quality"]
    print(
        f"| {case} | {1000 * bt.get('lpips_vgg', float('nan')):.1f} → {1000 * nt['lpips_vgg']:.1f} "
        f"| {bt.get('psnr', float('nan')):.2f} → {nt['psnr']:.2f} "
        f"| {1000 * bq.get('held_out', {}).get('lpips_vgg', float('nan')):.1f} → "
        f"{1000 * nq['held_out']['lpips_vgg']:.1f} "
        f"| {bq.get('verdict', '–')} → {nq['verdict']} "
        f"| {100 * b.get('max_std_m', float('nan')):.2f} → {100 * now['max_std_m']:.2f} |"
    )
print(f"\npoor above report LPIPS-VGG {rules.poor_lpips}; truth poor above 0.17")
