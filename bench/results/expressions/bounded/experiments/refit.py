"""The fit's face and refine stages run again from a dataset's stored fit, with stage overrides;
the fitted eye and mouth openings against the stored detections, over every frame. A copy of
``../../opening_weight_refit/refit_openings.py`` with three more keys: ``_config`` (FitConfig
fields), ``_save`` (a file for the fitted expression) and ``_face_iterations``; run from a tree
with ``../experiments.patch``.

    .venv/bin/python bench/results/expressions/opening_weight_refit/refit_openings.py DATASET \\
        '{"w_openings": 300.0}'          # a JSON of FitStage fields; '{"_none": 1}': the stored fit

A key ``_only`` (a list of stage names) limits the overrides to those stages. Prints one line:
the variant, the seconds, then per measure (``eval.expression_fidelity.openings``) Pearson r,
the detections' and the fit's 5-95 percentile ranges and the fit's range over the detections'.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time

import torch

from bench.expressions import stored_targets  # noqa: E402
from eva_engine.align.face_mesh import load_correspondence  # noqa: E402
from eva_engine.align.fit import fit_sequence  # noqa: E402
from eva_engine.align.stages import FitConfig  # noqa: E402
from eva_engine.body import load_body_model  # noqa: E402
from eva_engine.data import load_dataset  # noqa: E402
from eva_engine.eval.expression_fidelity import fitted_landmarks, openings  # noqa: E402


def summary(detected: torch.Tensor, fitted: torch.Tensor, name: str) -> str:
    ok = torch.isfinite(detected) & torch.isfinite(fitted)
    d, f = detected[ok], fitted[ok]
    q = torch.tensor([0.05, 0.95], dtype=d.dtype)
    (d0, d1), (f0, f1) = torch.quantile(d, q).tolist(), torch.quantile(f, q).tolist()
    r = float(torch.corrcoef(torch.stack([d, f]))[0, 1])
    return f"{name}: r {r:.3f} det {d0:.3f}-{d1:.3f} fit {f0:.3f}-{f1:.3f} ratio {(f1 - f0) / (d1 - d0):.2f}"


def main() -> None:
    torch.set_num_threads(1)
    ds = load_dataset(sys.argv[1])
    variant = json.loads(sys.argv[2]) if len(sys.argv) > 2 else {}
    model = load_body_model(ds.meta.body_model or "anny")
    reg, ids = load_correspondence(model).regressor(model)
    fields = {k: v for k, v in variant.items() if not k.startswith("_")}
    only = variant.get("_only")
    base = dataclasses.replace(FitConfig(), **variant.get("_config", {}))
    stages = tuple(
        dataclasses.replace(s, **fields) if only is None or s.name in only else s
        for s in base.stages
        if s.name in ("face", "refine")
    )
    if "_face_iterations" in variant:
        stages = tuple(
            dataclasses.replace(s, iterations=variant["_face_iterations"]) if s.name == "face" else s
            for s in stages
        )
    started = time.time()
    if variant.get("_none"):
        params = ds.params
    else:
        config = dataclasses.replace(base, stages=stages)
        params = fit_sequence(model, stored_targets(ds), init=ds.params, config=config).params
    if variant.get("_save"):
        torch.save({"expression": params.expression, "names": list(model.expression_names)}, variant["_save"])
    detected = openings(ds.keypoint_extras["face_mesh"])
    fitted = openings(fitted_landmarks(model, params, reg, ids, ds.K, ds.viewmat))
    cells = " | ".join(summary(detected[m], fitted[m], m) for m in ("eyes", "mouth"))
    print(json.dumps(variant), f"{time.time() - started:.0f}s |", cells, flush=True)


if __name__ == "__main__":
    main()
