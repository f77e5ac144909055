"""The held-out frames rendered with the fitted blinks times a gain (clamped to [0, 1]): does the
avatar's eye read as closed as the video's once its lids close further? (``README.md``)

    PYTHONPATH=. python bench/results/expressions/eye_binding/blink_gain.py DATASET AVATAR GAIN...

Prints, per gain, the render's eye opening against the target's over the ``test_pose`` frames
(MediaPipe on both, ``eval.expression_fidelity``): Pearson r and the range ratio.
"""

from __future__ import annotations

import dataclasses
import sys

import torch

from bench.expressions import detect_faces, to_uint8
from eva_engine.avatar import Camera, load_saved_avatar
from eva_engine.data import load_dataset
from eva_engine.eval.expression_fidelity import agreement, openings


def main(dataset: str, avatar_dir: str, *gains: str) -> None:
    torch.set_num_threads(1)
    ds = load_dataset(dataset)
    avatar = load_saved_avatar(avatar_dir).avatar.eval()
    names = list(avatar.body.expression_names)
    blinks = [names.index("eyeBlinkLeft"), names.index("eyeBlinkRight")]
    indices = list(ds.splits["test_pose"])
    frames = [ds[i] for i in indices]
    target = openings(*detect_faces([to_uint8(f.image) for f in frames]))["eyes"]
    for gain in map(float, gains):
        renders = []
        with torch.no_grad():
            for i, f in zip(indices, frames, strict=True):
                params = ds.params[i]
                expression = params.expression.clone()
                expression[..., blinks] = (expression[..., blinks] * gain).clamp(0, 1)
                params = dataclasses.replace(params, expression=expression)
                h, w = f.image.shape[:2]
                camera = Camera(f.K.float(), f.viewmat.float(), w, h)
                renders.append(to_uint8(avatar(params, camera, torch.ones(3)).image))
        got = agreement(target, openings(*detect_faces(renders))["eyes"])
        print(f"gain {gain}: eyes r {got.r:.2f}, range ratio {got.range_ratio:.2f}", flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
