"""The close-up's dataset fitted again from its stored detections by the job path's fit with one
change: ``python refit_variant.py <dataset> <out dataset> [stage:field=value ...]``, with
``HAND_DEPTH_SCALE=<x>`` (``FitConfig.hand_depth_scale``) or ``FOV=<degrees>`` (the cameras'
focal length set to that vertical field of view) in the environment."""

import dataclasses
import math
import os
import shutil
import sys
import time
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from bench.closeup_levers import Variant, preprocess_config
from bench.expressions import stored_targets
from eva_engine.align.clip import fit_clip
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.data.dataset import ParamNames, _save_params

torch.set_num_threads(1)
src, dst = Path(sys.argv[1]), Path(sys.argv[2])
stages = []
for spec in sys.argv[3:]:
    name, setting = spec.split(":")
    field, value = setting.split("=")
    stages.append((name, field, float(value)))
config = preprocess_config(Variant("refit", stages=tuple(stages))).fitting
if os.environ.get("HAND_DEPTH_SCALE"):
    config = dataclasses.replace(config, hand_depth_scale=float(os.environ["HAND_DEPTH_SCALE"]))
model = load_body_model("anny")
ds = load_dataset(src)
targets = stored_targets(ds)
if os.environ.get("FOV"):
    focal = (ds.image_size[0] / 2) / math.tan(math.radians(float(os.environ["FOV"])) / 2)
    ds.K = ds.K.clone()
    ds.K[:, 0, 0] = ds.K[:, 1, 1] = focal
    targets = dataclasses.replace(targets, K=ds.K)
start = time.time()
fit = fit_clip(model, targets, ds.timestamps, config)
print(f"fitted {len(ds)} frames in {time.time() - start:.0f} s")
if dst.exists():
    shutil.rmtree(dst)
shutil.copytree(src, dst)
(dst / "params.safetensors").unlink()
_save_params(dst / "params.safetensors", fit.params, ParamNames.of(model), "fitted")
cameras = load_file(dst / "cameras.safetensors")
cameras["K"] = ds.K.contiguous()
save_file(cameras, dst / "cameras.safetensors")
