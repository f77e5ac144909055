"""The default's and the spread's avatars away from the training views: a closed-eye frame of
the seated clip seen 35 degrees to the side, and a new pose (the rest pose, both blinks at 0.4)
from the front-left (``README.md``).

    python bench/results/expressions/colour_spread/new_views.py DATASET FRAME OUT.jpg AVATAR...
"""

from __future__ import annotations

import sys

import cv2
import numpy as np
import torch

from eva_engine.avatar import load_saved_avatar
from eva_engine.avatar.render_spec import frame_camera, frame_params, render_image

SIZE = (1152, 2048)
FACE = (0.25, 0.5, 0.3, 0.8)  # rows and columns of the frame holding the face (this clip)
BLINK = 0.4


def face_crop(image: np.ndarray, label: str) -> np.ndarray:
    h, w = image.shape[:2]
    crop = np.ascontiguousarray(
        image[int(h * FACE[0]) : int(h * FACE[1]), int(w * FACE[2]) : int(w * FACE[3])]
    )
    cv2.putText(crop, label, (5, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2)
    return crop


def views(avatar_dir: str, frame: int) -> np.ndarray:
    saved = load_saved_avatar(avatar_dir)
    avatar, frames = saved.avatar, saved.frames
    params = frame_params(frames, frame)
    side = frame_camera(avatar, frames, frame, params, 35.0, 0.0, *SIZE)
    new_pose = frame_params(frames, frame)
    new_pose.joints.zero_()  # the rest pose, in the frame's place
    names = list(avatar.body.expression_names)
    new_pose.expression.zero_()
    for name in ("eyeBlinkLeft", "eyeBlinkRight"):
        new_pose.expression[0, names.index(name)] = BLINK
    front_left = frame_camera(avatar, frames, frame, new_pose, -30.0, 10.0, *SIZE)
    row = [
        face_crop(render_image(avatar, params, side, (1.0, 1.0, 1.0)), f"frame {frame}, yaw 35"),
        face_crop(render_image(avatar, new_pose, front_left, (1.0, 1.0, 1.0)), f"rest, blink {BLINK}"),
    ]
    return np.concatenate(row, axis=1)


def main(dataset: str, frame: str, out: str, *avatars: str) -> None:
    torch.set_num_threads(2)
    sheet = np.concatenate([views(a, int(frame)) for a in avatars], axis=0)
    cv2.imwrite(out, cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])


if __name__ == "__main__":
    main(*sys.argv[1:])
