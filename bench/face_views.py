"""Face close-ups of an avatar from the video's side and turned away from it (issue 39): for the
held-out frames of a dataset where the fitted face is most open-mouthed, most closed-eyed and
most neutral, the target's face | the avatar's face seen from the video's camera | turned by each
``--yaws`` about the head (degrees, about the camera's up axis). A contact sheet (JPEG) and a
Markdown note with the command and the frames."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from bench.machine import header_line, run_header
from eva_engine.avatar import load_saved_avatar, read_avatar_meta
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset
from eva_engine.render.camera import Camera, intrinsics, look_at


def rotate(v: torch.Tensor, axis: torch.Tensor, degrees: float) -> torch.Tensor:
    """``v`` [3] turned about the unit ``axis`` (Rodrigues)."""
    a = math.radians(degrees)
    return v * math.cos(a) + torch.linalg.cross(axis, v) * math.sin(a) + axis * (axis @ v) * (1 - math.cos(a))


def pick_frames(dataset, ids: list[int], names: list[str]) -> dict[str, int]:
    """The held-out frames whose fitted face is most open-mouthed, most closed-eyed, most neutral."""
    expr = dataset.params.expression[ids]
    col = {n: i for i, n in enumerate(names)}
    jaw = expr[:, col["jawOpen"]]
    blink = (expr[:, col["eyeBlinkLeft"]] + expr[:, col["eyeBlinkRight"]]) / 2
    calm = expr.abs().sum(dim=1)
    return {
        "mouth open": ids[int(jaw.argmax())],
        "eyes closed": ids[int(blink.argmax())],
        "neutral": ids[int(calm.argmin())],
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--avatar", type=Path, required=True)
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--split", default="test_pose")
    p.add_argument("--yaws", type=float, nargs="+", default=[45.0, 90.0])
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--distance", type=float, default=0.55, help="metres from the head")
    p.add_argument("--fov", type=float, default=30.0)
    p.add_argument("--out", type=Path, required=True, help="the sheet (.jpg); the note beside it (.md)")
    p.add_argument("--note", default="")
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    ds = load_dataset(args.dataset)
    body = load_body_model(read_avatar_meta(args.avatar).body_model)
    avatar = load_saved_avatar(args.avatar, body=body).avatar.eval()
    ids = list(ds.splits[args.split])
    chosen = pick_frames(ds, ids, body.expression_names)
    head = body.joint_names.index("head")
    s = args.size
    K = intrinsics(s, s, args.fov)
    rows = []
    for i in chosen.values():
        frame, params = ds[i], ds.params[i]
        with torch.no_grad():
            h = body(params).joints[0, head]
        view = frame.viewmat.float()
        rot, trans = view[:3, :3], view[:3, 3]
        eye = -rot.T @ trans
        up = -rot[1]  # the video camera's up
        # The target's face: the head's box at this distance, from the frame.
        uvw = frame.K.float() @ (rot @ h + trans)
        u, v = float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2])
        half = float(frame.K[0, 0]) * args.distance * math.tan(math.radians(args.fov) / 2) / float(uvw[2])
        img = Image.fromarray((frame.image.numpy() * 255).astype(np.uint8))
        tiles = [
            img.crop((round(u - half), round(v - half), round(u + half), round(v + half))).resize((s, s))
        ]
        for yaw in [0.0, *args.yaws]:
            ahead = torch.nn.functional.normalize(rotate(eye - h, up, yaw), dim=0)
            camera = Camera(K, look_at(h + args.distance * ahead, h, up), s, s)
            with torch.no_grad():
                out = avatar.render(params, camera, torch.ones(3))
            tiles.append(Image.fromarray((out.numpy() * 255 + 0.5).astype(np.uint8)))
        rows.append(np.concatenate([np.asarray(t.convert("RGB")) for t in tiles], axis=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(args.out, quality=90)
    yaws = ", ".join(f"{y:g}°" for y in args.yaws)
    header = run_header()
    coverage = read_avatar_meta(args.avatar).coverage
    yaw = coverage.yaw_deg if coverage is not None else None
    yaw_range = f"{yaw.min:.1f}° to {yaw.max:.1f}°" if yaw is not None else "not recorded"
    lines = [
        "# Face close-ups from the video's camera and turned away from it",
        "",
        header_line(header),
        f"- machine: {header['machine']}",
        f"- avatar: `{args.avatar}`; dataset: `{args.dataset}`, split `{args.split}` (unseen frames)",
        f"- the training cameras' yaw about the body (the avatar's coverage): {yaw_range}",
        "- rows (the fitted face's extremes among them): "
        + ", ".join(f"{label} = frame {i}" for label, i in chosen.items()),
        f"- columns: the target (the frame, around the head) | the avatar from the video's side | "
        f"turned {yaws} about the head; {args.distance} m from the head, {args.fov:g}° field of view",
        "",
        f"![face views]({args.out.name})",
    ]
    if args.note:
        lines.insert(4, f"- note: {args.note}")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out} and its note")


if __name__ == "__main__":
    main()
