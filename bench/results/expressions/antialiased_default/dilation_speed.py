"""One render of a trained avatar at its frame's size, classic rasterization with 3DGS's 0.3 px²
dilation against the presets' 0.1: forward alone (a render request) and forward with backward (a
training step's rasterization), alternating, one thread. The avatar is the gesturing clip's
seed-0 ``ce01`` (this folder's README):

    PYTHONPATH=. python bench/results/expressions/antialiased_default/dilation_speed.py \\
        data/s40/gesturing data/s40/gesturing/avatar-ce01-s0
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from bench.machine import run_header
from eva_engine.avatar import Camera, load_saved_avatar
from eva_engine.data import load_dataset

EPS = (0.3, 0.1)


def main(dataset: Path, avatar_dir: Path, repeats: int = 8) -> None:
    torch.set_num_threads(1)
    ds = load_dataset(dataset)
    avatar = load_saved_avatar(avatar_dir).avatar
    i = ds.splits["test_pose"][0]
    frame = ds[i]
    h, w = ds.meta.image_size
    camera = Camera(frame.K.float(), frame.viewmat.float(), w, h)
    with torch.no_grad():
        posed = avatar.pose(ds.params[i])
    ms: dict[str, dict[str, list[float]]] = {"forward": {}, "forward_backward": {}}
    for _ in range(repeats):
        for eps in EPS:
            avatar.config = dataclasses.replace(avatar.config, eps2d=eps)
            with torch.no_grad():
                start = time.perf_counter()
                avatar.rasterize_posed(posed, camera, torch.ones(3))
                ms["forward"].setdefault(str(eps), []).append(1000 * (time.perf_counter() - start))
            means = posed.means.detach().clone().requires_grad_()
            start = time.perf_counter()
            out = avatar.rasterize_posed(dataclasses.replace(posed, means=means), camera, torch.ones(3))
            out.image.sum().backward()
            ms["forward_backward"].setdefault(str(eps), []).append(1000 * (time.perf_counter() - start))
    doc = {
        **run_header(),
        "avatar": str(avatar_dir),
        "image_size": [h, w],
        "gaussians": len(avatar.gaussians),
        "ms": ms,
        "median_ms": {k: {e: statistics.median(v) for e, v in d.items()} for k, d in ms.items()},
    }
    out = Path(__file__).with_suffix(".json")
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(doc["median_ms"]))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
