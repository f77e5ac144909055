"""refit_ds.py SRC DST JSON: the clip fitted again (full fit_clip) under a variant (a tree with
``../experiments.patch`` for its keys); writes DST (hard links)."""

import dataclasses
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

from bench.expressions import stored_targets
from eva_engine.align.clip import fit_clip
from eva_engine.align.face_mesh import load_correspondence
from eva_engine.align.stages import FitConfig
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.data.dataset import ParamNames, _save_params
from eva_engine.eval.expression_fidelity import fitted_landmarks, openings

torch.set_num_threads(1)
src, dst, variant = Path(sys.argv[1]), Path(sys.argv[2]), json.loads(sys.argv[3])
model = load_body_model("anny")
ds = load_dataset(src)
cfg = dataclasses.replace(FitConfig(), **variant.get("_config", {}))
fields = {k: v for k, v in variant.items() if not k.startswith("_")}
iters = variant.get("_iterations", {})
st = tuple(
    dataclasses.replace(
        s,
        **(fields if s.name in ("face", "refine", "outline") else {}),
        iterations=iters.get(s.name, s.iterations),
    )
    for s in cfg.stages
)
t0 = time.time()
fit = fit_clip(model, stored_targets(ds), ds.timestamps, dataclasses.replace(cfg, stages=st))
secs = time.time() - t0
reg, ids = load_correspondence(model).regressor(model)
det = openings(ds.keypoint_extras["face_mesh"])
f = openings(fitted_landmarks(model, fit.params, reg, ids, ds.K, ds.viewmat))
q = torch.tensor([0.05, 0.95], dtype=torch.float64)


def rr(m):
    d, g = det[m], f[m]
    ok = torch.isfinite(d) & torch.isfinite(g)
    d, g = d[ok], g[ok]
    (d0, d1), (g0, g1) = torch.quantile(d, q).tolist(), torch.quantile(g, q).tolist()
    return f"{m} r {float(torch.corrcoef(torch.stack([d, g]))[0, 1]):.3f} ratio {(g1 - g0) / (d1 - d0):.2f}"


print(src.name, "->", dst.name, json.dumps(variant), f"{secs:.0f}s", rr("eyes"), rr("mouth"), flush=True)
if dst.exists():
    shutil.rmtree(dst)
subprocess.run(["cp", "-al", str(src), str(dst)], check=True)
for p in dst.glob("avatar-*"):
    shutil.rmtree(p)
for p in dst.glob("eval-*"):
    p.unlink()
(dst / "params.safetensors").unlink()
_save_params(dst / "params.safetensors", fit.params, ParamNames.of(model), "fitted")
