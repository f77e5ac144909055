"""How large the trained colour offsets are: per action, over the Gaussians it recolours, the
median and 99th percentile of each offset's size (``||delta||``, SH units) and the share at the
clamp (``expression_colours.MAX_OFFSET`` on some channel) (``README.md``).

    PYTHONPATH=. python bench/results/expressions/lid_colours/offset_sizes.py \
        data/s40/gesturing/avatar-ce01-s1 data/s40/gesturing/avatar-lid6-s1 ...

Writes ``offset_sizes.{json,md}`` beside this script.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result

HERE = Path(__file__).resolve().parent


def sizes(avatar_dir: str) -> dict:
    """{action: {median, p99, at_clamp}} of one avatar's offsets, over the Gaussians each
    action recolours."""
    from eva_engine.avatar.expression_colours import MAX_OFFSET
    from eva_engine.avatar.io import load_avatar

    avatar = load_avatar(avatar_dir)
    g = avatar.gaussians
    offsets = g.splats["sh0_expression"].detach()  # [N, K, 3]
    reach = avatar.expression_reach[g.vertex_ids]  # [N, K]
    names = [avatar.body.expression_names[i] for i in avatar.expression_actions.tolist()]
    out = {}
    for k, name in enumerate(names):
        d = offsets[reach[:, k], k]  # [M, 3]
        size = d.norm(dim=-1).double()
        q = torch.quantile(size, torch.tensor([0.5, 0.99], dtype=torch.float64)).tolist()
        at_clamp = float((d.abs().amax(dim=-1) >= MAX_OFFSET * 0.999).double().mean())
        out[name] = {"gaussians": int(d.shape[0]), "median": q[0], "p99": q[1], "at_clamp": at_clamp}
    return out


def main(*avatars: str) -> None:
    found = {Path(a).name: sizes(a) for a in avatars}
    doc = {**run_header(), "avatar_dirs": list(avatars), "avatars": found}
    lines = ["# The colour offsets' sizes", "", header_line(doc), ""]
    lines += [
        "Per action, over the Gaussians it recolours: the median and 99th percentile of the offset's "
        "size (SH units; 1 is 0.28 of the colour range) and the share of offsets at the clamp.",
        "",
        "| avatar | action | Gaussians | median | p99 | at the clamp |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for avatar, actions in found.items():
        for name, s in actions.items():
            lines.append(
                f"| {avatar} | {name} | {s['gaussians']} | {s['median']:.2f} | {s['p99']:.2f} "
                f"| {s['at_clamp']:.1%} |"
            )
    write_result(HERE, "offset_sizes", doc, lines)


if __name__ == "__main__":
    main(*sys.argv[1:])
