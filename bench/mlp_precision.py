"""The weight-offset MLP in float32 and in bfloat16 (issue 38): one training step's forward and
backward of ``LBSWeightOffsets.skinning_weights`` (EVA §3.1's f_w with the log prior and the
softmax), at the avatar's default size (39 -> 128 -> 128 -> 104), timed per Gaussian count.

    .venv/bin/python -m bench mlp_precision --threads 2

Also the bfloat16 step's largest weight difference and its gradients' relative error against
float32 on the same inputs (random centres; the MLP at its trained scale, not its near-zero
init, so the difference is not flattered). Writes ``bench/results/mlp_precision.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result
from bench.timing import time_call

RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", default="10000,30000,50000", help="Gaussian counts")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--name", default="mlp_precision")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    from eva_engine.avatar.networks import LBSWeightOffsets

    gen = torch.Generator().manual_seed(0)
    joints, vertices = 104, 13718  # Anny's bones and vertices
    net = LBSWeightOffsets(joints, 6, 128, 2, 0.5, gen)
    log_base = torch.log_softmax(torch.randn(vertices, joints, generator=gen), dim=-1)
    rows_out = [measure(net, log_base, int(n), args.repeats, gen) for n in args.sizes.split(",")]
    doc = {
        **run_header(),
        "bf16_native": bool(torch.ops.mkldnn._is_mkldnn_bf16_supported()),
        "rows": rows_out,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_result(args.out, args.name, doc, markdown(doc))
    print(markdown(doc))


def measure(net, log_base: torch.Tensor, n: int, repeats: int, gen: torch.Generator) -> dict:
    """One row: both precisions' step times at ``n`` Gaussians, and bfloat16's error."""
    joints, vertices = log_base.shape[1], log_base.shape[0]
    means = (0.5 * torch.randn(n, 3, generator=gen)).requires_grad_(True)
    rows = torch.randint(0, vertices, (n,), generator=gen)
    probe = torch.randn(n, joints, generator=gen)
    wrt = [means, *net.parameters()]

    def step(bf16: bool) -> tuple[torch.Tensor, tuple]:
        w = net.skinning_weights(means, log_base, rows, bf16=bf16)
        return w.detach(), torch.autograd.grad((w * probe).sum(), wrt)

    row: dict = {"gaussians": n}
    for bf16 in (False, True):
        row["bf16_ms" if bf16 else "fp32_ms"] = time_call(lambda b=bf16: step(b), repeats=repeats, warmup=3)
    (w32, g32), (w16, g16) = step(False), step(True)
    row["max_weight_diff"] = float((w16 - w32).abs().max())
    row["grad_rel_err"] = [float((a - b).norm() / b.norm()) for a, b in zip(g16, g32, strict=True)]
    print(row, file=sys.stderr, flush=True)
    return row


def markdown(doc: dict) -> str:
    lines = [
        "# The weight-offset MLP: float32 against bfloat16 products",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}; native bfloat16 (oneDNN): {doc['bf16_native']}",
        "",
        "One training step of `LBSWeightOffsets.skinning_weights` (forward and backward, median of the "
        "repeats, ms). Error: the bfloat16 step's largest skinning-weight difference, and the relative "
        "error of its gradients (centres, then each layer's weight and bias) against float32.",
        "",
        "| Gaussians | float32 ms | bfloat16 ms | speed-up | max weight diff | gradient rel. error |",
        "|---:|---:|---:|---:|---:|---|",
    ]
    for r in doc["rows"]:
        f32, b16 = r["fp32_ms"]["median_ms"], r["bf16_ms"]["median_ms"]
        errs = ", ".join(f"{e:.3f}" for e in r["grad_rel_err"])
        lines.append(
            f"| {r['gaussians']:,} | {f32:.1f} | {b16:.1f} | {f32 / b16:.2f}x "
            f"| {r['max_weight_diff']:.1e} | {errs} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
