"""Copy a dataset (hard links) with its clip fitted again by this tree under a fit variant from
the environment (FACE_ITERS, W_OPEN, CALIB): refit_dataset.py SRC DST."""

import dataclasses
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

from bench.expressions import stored_targets
from eva_engine.align.clip import fit_clip
from eva_engine.align.stages import FitConfig
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.data.dataset import ParamNames, _save_params

torch.set_num_threads(1)
src, dst = Path(sys.argv[1]), Path(sys.argv[2])
model = load_body_model("anny")
ds = load_dataset(src)
targets = stored_targets(ds)
cfg = FitConfig(
    detector_calibration=os.environ.get("CALIB", "1") == "1",
    relative_lids=os.environ.get("RELLIDS", "0") == "1",
)
over = {"w_openings": float(os.environ["W_OPEN"])} if "W_OPEN" in os.environ else {}
st = tuple(
    dataclasses.replace(s, **(over if s.name in ("face", "refine", "outline") else {})) for s in cfg.stages
)
if "FACE_ITERS" in os.environ:
    st = tuple(
        dataclasses.replace(s, iterations=int(os.environ["FACE_ITERS"])) if s.name == "face" else s
        for s in st
    )
t0 = time.time()
fit = fit_clip(model, targets, ds.timestamps, dataclasses.replace(cfg, stages=st))
print(f"fitted {len(ds)} frames in {time.time() - t0:.0f} s", flush=True)
if dst.exists():
    shutil.rmtree(dst)
subprocess.run(["cp", "-al", str(src), str(dst)], check=True)
(dst / "params.safetensors").unlink()
_save_params(dst / "params.safetensors", fit.params, ParamNames.of(model), "fitted")
print("wrote", dst)
