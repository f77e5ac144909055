"""Copy a dataset fitted with ``FitConfig.expression_sigma`` = 0 and apply the old default's
smoothing (0.04 s) to its stored expressions: the old pipeline's output, since the smoothing was
the fit's last step and touched the expression only.

    python make_smoothed.py <unsmoothed dataset> <new dataset folder>
"""

import shutil
import sys

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from eva_engine.align.clip import smooth_over_time
from eva_engine.data import load_dataset

OLD_SIGMA_S = 0.04

src, dst = sys.argv[1], sys.argv[2]
shutil.copytree(src, dst)
times = torch.as_tensor(load_dataset(src).timestamps, dtype=torch.float64)
path = f"{dst}/params.safetensors"
with safe_open(path, "pt") as f:
    meta = f.metadata()
    tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open has no __iter__)
tensors["expression"] = smooth_over_time(tensors["expression"], times, OLD_SIGMA_S).contiguous()
save_file(tensors, path, metadata=meta)
print(f"wrote {dst}: {tensors['expression'].shape[0]} frames' expressions smoothed by {OLD_SIGMA_S} s")
