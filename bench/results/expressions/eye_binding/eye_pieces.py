"""Where a rendered eye's pixels come from: the test frames with the largest fitted blinks and the
most open one, each a row of the eyes at 4x the frame's pixels (``README.md``):

target | render | render without the blinks' colour offsets | the Gaussians coloured by the mesh
piece of their vertex (red: the lid's skin, the head vertices a blink moves by over a tenth of
its largest travel; green: the eyeball's front and back; blue: the eye socket; grey: the rest) |
the lid's Gaussians alone, in red.

    PYTHONPATH=. python bench/results/expressions/eye_binding/eye_pieces.py DATASET AVATAR OUT.png [N]

Prints the Gaussians per piece with their mean opacity and size.
"""

from __future__ import annotations

import copy
import sys

import cv2
import numpy as np
import torch

from eva_engine.avatar import Camera, load_saved_avatar
from eva_engine.body.anny_backend import SEGMENT_LABELS
from eva_engine.data import load_dataset

C0 = 0.28209479177387814  # SH DC basis
UP = 4  # render at 4x the frame's pixels
EYES = [33, 133, 362, 263, 159, 145, 386, 374, 70, 300]  # face-mesh landmarks around both eyes
PALETTE = torch.tensor([[0.6, 0.6, 0.6], [1.0, 0.0, 0.0], [0.0, 0.8, 0.0], [0.0, 0.0, 1.0]])
PIECES = ("rest", "lid", "eyeball", "socket")


def piece_of_vertices(avatar) -> torch.Tensor:
    """[V] index into ``PIECES`` of each template vertex."""
    body = avatar.body
    labels = torch.as_tensor(body.segment_labels)
    names = list(body.expression_names)
    p = body.default_params(2)
    p.shape[:] = avatar.shape
    p.expression[1, [names.index("eyeBlinkLeft"), names.index("eyeBlinkRight")]] = 1.0
    with torch.no_grad():
        rest = body.canonical(p)
    travel = (rest[1] - rest[0]).norm(dim=-1)
    piece = torch.zeros(len(labels), dtype=torch.long)
    for v, i in enumerate(labels.tolist()):
        name = SEGMENT_LABELS[i]
        if name.startswith(("eye_front", "eye_back")):
            piece[v] = 2
        elif name.startswith("eye_cavity"):
            piece[v] = 3
    piece[(travel > 0.1 * travel.max()) & (piece == 0)] = 1
    return piece


def variant(avatar, kind: str, piece: torch.Tensor):
    out = copy.deepcopy(avatar)
    s = out.gaussians.splats
    with torch.no_grad():
        if "sh0_expression" in s:
            s["sh0_expression"].zero_()
        if kind in ("pieces", "lid"):
            s["sh0"].copy_(((PALETTE[piece] - 0.5) / C0)[:, None, :])
            s["shN"].zero_()
        if kind == "lid":
            s["opacities"][piece != 1] = -30.0
    return out


def main(dataset: str, avatar_dir: str, out: str, n: str = "3") -> None:
    torch.set_num_threads(2)
    ds = load_dataset(dataset)
    avatar = load_saved_avatar(avatar_dir).avatar.eval()
    names = list(avatar.body.expression_names)
    blinks = [names.index("eyeBlinkLeft"), names.index("eyeBlinkRight")]
    test = list(ds.splits["test_pose"])
    blink = ds.params.expression[test][:, blinks].mean(dim=1)
    order = torch.argsort(blink, descending=True).tolist()
    picks = [test[i] for i in order[: int(n)]] + [test[order[-1]]]
    piece = piece_of_vertices(avatar)[avatar.gaussians.vertex_ids]
    opacity = torch.sigmoid(avatar.gaussians.splats["opacities"].detach()).squeeze(-1)
    size = torch.exp(avatar.gaussians.splats["scales"].detach()).mean(dim=-1)
    for k, name in enumerate(PIECES):
        sel = piece == k
        print(
            f"{name}: {int(sel.sum())} Gaussians, mean opacity {float(opacity[sel].mean()):.3f}, "
            f"mean scale {float(size[sel].mean()) * 1000:.2f} mm"
        )
    renders = [avatar, variant(avatar, "no colours", piece), variant(avatar, "pieces", piece)]
    renders.append(variant(avatar, "lid", piece))
    marks = ds.keypoint_extras["face_mesh"]
    rows = []
    for i in picks:
        f = ds[i]
        h, w = f.image.shape[:2]
        cam = Camera(f.K.float(), f.viewmat.float(), w, h).scaled(UP)
        xy = marks[i, EYES, :2] * UP
        lo, hi = xy.min(0).values, xy.max(0).values
        cx, cy = (lo + hi) / 2
        half = float((hi - lo).max()) * 0.65
        x0, x1, y0, y1 = int(cx - half), int(cx + half), int(cy - half / 2), int(cy + half / 2)
        target = (f.image.numpy() * 255).astype(np.uint8)
        tiles = [cv2.resize(target, (w * UP, h * UP), interpolation=cv2.INTER_CUBIC)[y0:y1, x0:x1]]
        with torch.no_grad():
            for a in renders:
                img = a(ds.params[i], cam, torch.ones(3)).image.clamp(0, 1).numpy()
                tiles.append((img[y0:y1, x0:x1] * 255).astype(np.uint8))
        tiles = [cv2.resize(t, (400, 200)) for t in tiles]
        label = f"frame {i}, blink {float(ds.params.expression[i, blinks].mean()):.2f}"
        cv2.putText(tiles[0], label, (5, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 0, 0), 2)
        rows.append(np.concatenate(tiles, axis=1))
    cv2.imwrite(out, cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    main(*sys.argv[1:])
