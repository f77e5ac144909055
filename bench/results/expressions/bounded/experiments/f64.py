"""f64.py DATASET JSON: the face and refine stages again from the stored fit under a variant (a tree with
``../experiments.patch``), with the loss evaluations per stage; ``_f64``: in float64."""

import dataclasses
import json
import sys
import time

import torch

from bench.expressions import stored_targets
from eva_engine.align.face_mesh import load_correspondence
from eva_engine.align.fit import fit_sequence
from eva_engine.align.stages import FitConfig
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.eval.expression_fidelity import fitted_landmarks, openings

torch.set_num_threads(1)
ds = load_dataset(sys.argv[1])
variant = json.loads(sys.argv[2])
model = load_body_model("anny")
if variant.get("_f64"):
    model = model.double()
fields = {k: v for k, v in variant.items() if not k.startswith("_")}
base = dataclasses.replace(FitConfig(), **variant.get("_config", {}))
only = variant.get("_only", ["face", "refine"])
stages = tuple(
    dataclasses.replace(s, **fields) if s.name in only else s
    for s in base.stages
    if s.name in ("face", "refine")
)
calls = {}
t0 = time.time()


def prog(e):
    calls[e.stage] = calls.get(e.stage, 0) + 1


init = ds.params.map(lambda t: t.to(model.dtype))
tg = stored_targets(ds)
if variant.get("_f64"):
    for k, v in list(vars(tg).items()):
        if torch.is_tensor(v):
            setattr(tg, k, v.double())
res = fit_sequence(model, tg, init=init, config=dataclasses.replace(base, stages=stages), progress=prog)
m32 = load_body_model("anny")
reg, ids = load_correspondence(m32).regressor(m32)
p = res.params.map(lambda t: t.float())
det = openings(ds.keypoint_extras["face_mesh"])
fit = openings(fitted_landmarks(m32, p, reg, ids, ds.K, ds.viewmat))
q = torch.tensor([0.05, 0.95], dtype=torch.float64)


def rr(m):
    d, f = det[m], fit[m]
    ok = torch.isfinite(d) & torch.isfinite(f)
    d, f = d[ok], f[ok]
    (d0, d1), (f0, f1) = torch.quantile(d, q).tolist(), torch.quantile(f, q).tolist()
    return f"{m} r {float(torch.corrcoef(torch.stack([d, f]))[0, 1]):.3f} ratio {(f1 - f0) / (d1 - d0):.2f}"


print(
    sys.argv[1].split("/")[-1],
    json.dumps(variant),
    calls,
    f"{time.time() - t0:.0f}s",
    rr("eyes"),
    rr("mouth"),
    flush=True,
)
if variant.get("_save"):
    torch.save({"expression": res.params.expression.float()}, variant["_save"])
