"""One training frame of closed eyes rendered four ways: as fitted, without the expression's
colour offsets, and with both blinks set to 1 and to 0 (``README.md``).

    python bench/results/expressions/train_split/closed_eye_variants.py AVATAR FRAME OUT.png

Prints the frame's fitted blink coefficients (``closed_eye_variants_*.txt``).
"""

from __future__ import annotations

import sys

import cv2
import numpy as np
import torch

from eva_engine.avatar import load_saved_avatar
from eva_engine.avatar.render_spec import frame_camera, frame_params, render_image

VARIANTS = ("as fitted", "no colour offsets", "blink 1.0", "blink 0")
BLINKS = ("eyeBlinkLeft", "eyeBlinkRight")
SIZE = (1152, 2048)  # the 1080p video's aspect at about its resolution
EYES = (0.33, 0.41, 0.38, 0.72)  # rows and columns of the frame holding the eyes (this clip)


def render(avatar_dir: str, frame: int, variant: str) -> np.ndarray:
    saved = load_saved_avatar(avatar_dir)  # afresh: the avatar keeps its last pose
    avatar, frames = saved.avatar, saved.frames
    names = list(avatar.body.expression_names)
    params = frame_params(frames, frame)
    if variant == "no colour offsets":
        with torch.no_grad():
            avatar.gaussians.splats["sh0_expression"].zero_()
    elif variant.startswith("blink"):
        for name in BLINKS:
            params.expression[0, names.index(name)] = float(variant.split()[1])
    camera = frame_camera(avatar, frames, frame, params, 0.0, 0.0, *SIZE)
    image = render_image(avatar, params, camera, (1.0, 1.0, 1.0))
    h, w = image.shape[:2]
    crop = image[int(h * EYES[0]) : int(h * EYES[1]), int(w * EYES[2]) : int(w * EYES[3])]
    crop = np.ascontiguousarray(cv2.resize(crop, None, fx=2, fy=2))
    cv2.putText(crop, variant, (5, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 255), 2)
    return crop


def main(avatar_dir: str, frame: str, out: str) -> None:
    torch.set_num_threads(2)
    saved = load_saved_avatar(avatar_dir)
    fitted = frame_params(saved.frames, int(frame)).expression[0]
    names = list(saved.avatar.body.expression_names)
    print(f"frame {frame}, fitted: " + ", ".join(f"{n} {float(fitted[names.index(n)]):.2f}" for n in BLINKS))
    sheet = np.concatenate([render(avatar_dir, int(frame), v) for v in VARIANTS], axis=0)
    cv2.imwrite(out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main(*sys.argv[1:])
