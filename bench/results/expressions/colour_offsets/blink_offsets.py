"""Where a trained avatar's blink colour offsets push, and how far: per blink action, the
Gaussians it recolours (nonzero offset), those whose offset sits at the clamp
(``expression_colours.MAX_OFFSET``), whether the offsets lighten or darken, and where those
Gaussians lie (their canonical means against the body's eye joints, in millimetres; below the
eye: negative y). ``python blink_offsets.py <avatar folder> [...]`` from the repository."""

import sys

import torch

from eva_engine.avatar.expression_colours import MAX_OFFSET
from eva_engine.avatar.io import load_saved_avatar
from eva_engine.render.sh import SH_C0

for folder in sys.argv[1:]:
    saved = load_saved_avatar(folder)
    avatar = saved.avatar
    g = avatar.gaussians
    offsets = g.splats["sh0_expression"].detach()  # [N, K, 3]
    base = 0.5 + SH_C0 * g.splats["sh0"].detach().reshape(-1, 3)
    means = g.splats["means"].detach()
    body = avatar.body
    rest = body(avatar.subject_params(body.default_params(1)))
    eyes = {side: rest.joints[0, body.joint_names.index(f"eye.{side}")] for side in ("L", "R")}
    print(f"## {folder}")
    print(
        "| action | recoloured | at the clamp | mean colour change at the largest blink | darker | "
        "lighter | at the clamp: darker | at the clamp: mm from the nearer eye joint, median (x, y, z) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for k, name in enumerate(("eyeBlinkLeft", "eyeBlinkRight")):
        o = offsets[:, k]
        moved = o.abs().amax(-1) > 1e-6
        clamped = (o.abs() >= MAX_OFFSET * 0.999).any(-1)
        change = (SH_C0 * o).mean(-1)  # [N] the grey-level change at the largest training blink
        near = torch.stack([(means - e).norm(dim=-1) for e in eyes.values()], -1).argmin(-1)
        centre = torch.stack(list(eyes.values()))[near]
        rel = (means - centre)[clamped] * 1000
        med = rel.median(dim=0).values.tolist() if clamped.any() else [float("nan")] * 3
        print(
            f"| {name} | {int(moved.sum())} | {int(clamped.sum())} | {change[moved].mean():+.2f} "
            f"| {int((change[moved] < 0).sum())} | {int((change[moved] > 0).sum())} "
            f"| {int((change[clamped] < 0).sum())} | {med[0]:.0f}, {med[1]:.0f}, {med[2]:.0f} |"
        )
    at_clamp = (offsets.abs() >= MAX_OFFSET * 0.999).any(-1).any(-1)  # [N], either blink
    print(f"\nbase colour of the clamped ones, median grey: {base[at_clamp].mean(-1).median():.2f}\n")
