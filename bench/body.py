"""Body-model speed: forward and forward+backward at batch 1 and 150 (a whole clip), on CPU.

    .venv/bin/python -m bench body [--threads 2] [--repeats 5] [--backends anny smplx]

"forward" is ``model(params)`` plus ``model.keypoints(out)``; "forward+backward" adds the
backward pass of a loss on vertices and keypoints to every parameter (pose, root, translation,
shape, expression), as in fitting. SMPL-X runs only when ``$EVA_SMPLX_DIR`` points at real
files. Writes ``bench/results/body.json`` and ``body.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import torch

from bench.machine import cpu_name, run_header, write_result
from bench.timing import time_call
from eva_engine.body import load_body_model

RESULTS = Path(__file__).resolve().parent / "results"


def bench_model(model, batch: int, repeats: int) -> dict:
    g = torch.Generator().manual_seed(0)
    params = model.default_params(batch)
    params.joints.copy_(torch.randn(params.joints.shape, generator=g) * 0.3)
    params.root_orient.copy_(torch.randn(params.root_orient.shape, generator=g))

    def forward():
        with torch.no_grad():
            out = model(params)
            model.keypoints(out)

    def forward_backward():
        p = params.map(lambda t: t.detach().requires_grad_(True))
        out = model(p)
        loss = out.vertices.square().mean() + model.keypoints(out).square().mean()
        loss.backward()

    def keypoints_forward_backward():
        # The fitting path: keypoints only, shape shared by the clip (posed_keypoints).
        p = params.map(lambda t: t.detach().requires_grad_(True))
        shared = p.shape[:1].expand_as(p.shape)
        p = type(p)(p.root_orient, p.transl, p.joints, p.expression, shared)
        model.posed_keypoints(p)[0].square().mean().backward()

    return {
        "forward": time_call(forward, repeats),
        "forward_backward": time_call(forward_backward, repeats),
        "keypoints_forward_backward": time_call(keypoints_forward_backward, repeats),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 150])
    parser.add_argument("--backends", nargs="+", default=["anny", "smplx"])
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    results: dict = {}
    for name in args.backends:
        if name == "smplx" and not os.environ.get("EVA_SMPLX_DIR"):
            print("smplx: skipped ($EVA_SMPLX_DIR not set; SMPL-X files are licensed)")
            continue
        start = time.perf_counter()
        model = load_body_model(name)
        load_s = time.perf_counter() - start
        results[name] = {"load_s": load_s, "vertices": model.num_vertices, "joints": model.num_joints}
        for batch in args.batches:
            repeats = args.repeats if batch < 32 else max(2, args.repeats // 2)
            results[name][f"batch_{batch}"] = r = bench_model(model, batch, repeats)
            print(
                f"{name} B={batch}: forward {r['forward']['median_ms']:.1f} ms, "
                f"forward+backward {r['forward_backward']['median_ms']:.1f} ms, "
                f"keypoints-only forward+backward {r['keypoints_forward_backward']['median_ms']:.1f} ms"
            )

    record = {
        **run_header(),
        "machine": {
            "cpu": cpu_name(),
            "logical_cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "torch": torch.__version__,
        },
        "note": "CPU shared with other jobs when recorded; timings are noisy.",
        "results": results,
    }
    lines = [
        "# Body model benchmark",
        "",
        f"- date: {record['date']}",
        f"- command: `{record['command']}`",
        f"- machine: {record['machine']['cpu']}, {record['machine']['logical_cpus']} logical CPUs, "
        f"torch {record['machine']['torch']} with {record['machine']['torch_threads']} threads, "
        f"{record['machine']['platform']}",
        f"- note: {record['note']}",
        "",
        "| backend | batch | forward (ms) | forward+backward (ms) | keypoints-only forward+backward (ms) |",
        "|---|---:|---:|---:|---:|",
    ]
    keys = ("forward", "forward_backward", "keypoints_forward_backward")
    for name, r in results.items():
        for batch in args.batches:
            fwd, fwd_bwd, kp = (r[f"batch_{batch}"][k]["median_ms"] for k in keys)
            lines.append(f"| {name} | {batch} | {fwd:.1f} | {fwd_bwd:.1f} | {kp:.1f} |")
    lines += [
        "",
        "Medians over the repeats (min in body.json); model load times in body.json. forward: posed mesh "
        "(13,718 vertices) + keypoints; keypoints-only: `posed_keypoints` (keypoint-space LBS, shape "
        "shared by the clip), what alignment calls.",
    ]
    write_result(args.out, "body", record, lines)


if __name__ == "__main__":
    main()
