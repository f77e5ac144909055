"""Wall time of fit_clip on wild's 150 frames (bench align's clip), 1 thread; detection cached."""

import pathlib
import pickle
import sys
import tempfile
import time

import numpy as np
import torch

from eva_engine.align import detect_frames
from eva_engine.align.clip import fit_clip
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.paths import data_dir

torch.set_num_threads(1)
model = load_body_model("anny")
ds = load_dataset(data_dir() / "synthetic" / "wild-bench-seed0")
order = sorted(ds.splits["train"] + ds.splits["test_pose"])[:150]
cache = pathlib.Path(tempfile.gettempdir()) / "wild_targets.pkl"
if cache.exists():
    targets = pickle.loads(cache.read_bytes())
else:
    images = (ds.images(order).numpy() * 255 + 0.5).astype(np.uint8)
    targets = detect_frames(iter(images)).targets(ds.K[order], ds.viewmat[order])
    cache.write_bytes(pickle.dumps(targets))
t0 = time.perf_counter()
r = fit_clip(model, targets, ds.timestamps[order])
dt = time.perf_counter() - t0
print(f"{sys.argv[1]}: fit_clip 150 frames {dt:.1f} s", flush=True)
