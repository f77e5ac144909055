"""Where one render of a saved avatar spends its time (the render endpoint's work): posing
(``Avatar.pose``), projection, tile binning, compositing (each with the compiled kernels, as the
service runs them), the whole ``render_image`` call and the PNG encoding, at each ``--threads``.
Medians over ``--repeats`` after a warm-up, in one process on an otherwise idle machine.

    .venv/bin/python -m bench render_stages --avatar AVATAR_DIR --name render_stages \\
        --out bench/results/service_latency

Writes ``<name>.json`` and ``<name>.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, run_header, write_result
from bench.timing import time_call


def median_ms(fn, repeats: int) -> float:
    return time_call(fn, repeats)["median_ms"]


def png(image: np.ndarray) -> bytes:
    """PNG as the render endpoint encodes it (``service.rendering.encode_image``)."""
    from service.rendering import encode_image

    return encode_image(image, "png")


def measure(avatar_dir: Path, size: int, threads: int, repeats: int) -> dict:
    from eva_engine.avatar import load_saved_avatar
    from eva_engine.avatar.render_spec import render_image
    from eva_engine.render import bin_gaussians, composite_image, project_gaussians
    from eva_engine.render.view import camera_from_spec
    from eva_engine.specs.camera import CameraSpec

    torch.set_num_threads(threads)
    avatar = load_saved_avatar(avatar_dir).avatar
    params = avatar.body.default_params(1)
    turns = iter(range(1, 10**9))

    def new_pose():
        """The rest pose turned by a new 1e-5 rad each call: a pose the avatar has not just posed
        (``Avatar.pose`` keeps the last one for a request that changes only the camera)."""
        turned = params.map(torch.clone)
        turned.root_orient[0, 1] = 1e-5 * next(turns)
        return turned

    names = list(avatar.body.expression_names)
    face = [names.index(n) for n in ("jawOpen", "eyeBlinkLeft", "eyeBlinkRight") if n in names]

    def new_face():
        """A new pose with the jaw open 0.3 and the eyes half shut: the skin's frames carry the
        Gaussians the expression moves (``avatar/surface_frames.py``)."""
        posed = new_pose()
        posed.expression[0, face] = torch.tensor([0.3, 0.5, 0.5][: len(face)], dtype=posed.expression.dtype)
        return posed

    camera = camera_from_spec(CameraSpec(), size, size)
    background = torch.ones(3)
    with torch.no_grad():
        posed = avatar.pose(params)
        proj = project_gaussians(posed.means, posed.quats, posed.scales, camera.viewmat, camera.K, size, size)
        opacities = posed.opacities
        colors = torch.full((len(opacities), 3), 0.5)
        bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, size, size, 8, proj.conics, opacities)

        def project():
            project_gaussians(posed.means, posed.quats, posed.scales, camera.viewmat, camera.K, size, size)

        def bin_():
            bin_gaussians(proj.means2d, proj.radii, proj.depths, size, size, 8, proj.conics, opacities)

        def composite():
            composite_image(
                proj.means2d, proj.conics, opacities, colors, proj.depths, bins, size, size, background
            )

        image = render_image(avatar, params, camera, (1.0, 1.0, 1.0))
        return {
            "size": size,
            "threads": threads,
            "gaussians": len(opacities),
            "pairs": bins.num_intersections,
            "png_bytes": len(png(np.asarray(image))),
            "ms": {
                "pose": median_ms(lambda: avatar.pose(new_pose()), repeats),
                "pose_face": median_ms(lambda: avatar.pose(new_face()), repeats),
                "project": median_ms(project, repeats),
                "bin": median_ms(bin_, repeats),
                "composite": median_ms(composite, repeats),
                "render_image": median_ms(
                    lambda: render_image(avatar, new_pose(), camera, (1.0, 1.0, 1.0)), repeats
                ),
                "same_pose": median_ms(
                    lambda: render_image(avatar, params, camera, (1.0, 1.0, 1.0)), repeats
                ),
                "png": median_ms(lambda: png(np.asarray(image)), repeats),
            },
        }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--avatar", type=Path, required=True)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--note", default=None)
    ap.add_argument("--name", default="render_stages")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    rows = [measure(args.avatar, args.size, t, args.repeats) for t in args.threads]
    doc = {
        **run_header(),
        "note": args.note,
        "rows": rows,
    }
    stages = list(rows[0]["ms"])
    lines = [
        "# One render's stages",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        *([f"- note: {args.note}"] if args.note else []),
        f"- avatar: `{args.avatar}`, {rows[0]['gaussians']} Gaussians, rest pose, front camera, "
        f"{args.size}² px, {rows[0]['pairs']} Gaussian-tile pairs (8 px tiles, the default), a PNG of "
        f"{rows[0]['png_bytes'] / 1024:.1f} KB; medians of "
        f"{args.repeats} calls (ms); the stages one by one on the same posed Gaussians; render_image: "
        "the whole render (pose, SH colours, rasterize) of a new pose, as the endpoint calls it; "
        "pose_face: posing a new pose with the jaw open 0.3 and both eyes half shut; "
        "same_pose: the same of the pose posed last (a request that changes only the camera)",
        "",
        "| threads | " + " | ".join(stages) + " |",
        "|---:|" + "---:|" * len(stages),
        *(f"| {r['threads']} | " + " | ".join(f"{r['ms'][s]:.1f}" for s in stages) + " |" for r in rows),
    ]
    write_result(args.out, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
