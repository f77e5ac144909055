"""One 512 px render of a trained avatar, forward and backward, classic against antialiased
rasterization: six alternating runs each, one thread. The avatar is the default's of seed 0
(``frame_faces.py``'s ``base-s0``):

    python bench/results/novel_pose_closeups/antialiased_speed.py <tmp>/base-s0
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
from bench.novel_pose import dataset_for
from eva_engine.avatar import Camera, load_saved_avatar
from eva_engine.data import load_dataset


def main(avatar_dir: Path, repeats: int = 6) -> None:
    torch.set_num_threads(1)
    ds = load_dataset(dataset_for("bench", 0))
    avatar = load_saved_avatar(avatar_dir).avatar
    frame = ds[0]
    camera = Camera(frame.K.float(), frame.viewmat.float(), 512, 512)
    with torch.no_grad():
        posed = avatar.pose(ds.gt_params[0])
    ms: dict[str, list[float]] = {"classic": [], "antialiased": []}
    for _ in range(repeats):
        for mode in ms:
            avatar.config = dataclasses.replace(avatar.config, rasterize_mode=mode)
            means = posed.means.detach().clone().requires_grad_()
            start = time.perf_counter()
            out = avatar.rasterize_posed(dataclasses.replace(posed, means=means), camera, torch.ones(3))
            out.image.sum().backward()
            ms[mode].append(1000 * (time.perf_counter() - start))
    doc = {
        **run_header(),
        "gaussians": len(avatar.gaussians),
        "ms": ms,
        "median_ms": {mode: statistics.median(v) for mode, v in ms.items()},
    }
    out = Path(__file__).with_suffix(".json")
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(doc["median_ms"]))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
