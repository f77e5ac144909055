"""What a trained avatar's blink offsets learnt: per blink, the Gaussians it recolours, their
vertices, and the spread of their colours at the blink's full training extent (rest colour plus
offset, linear RGB before the renderer's clamp) within and between vertices, with their mean
opacity. Usage: python lid_colours.py OUT.json AVATAR_DIR..."""

import json
import sys

import torch

from eva_engine.avatar.io import load_avatar
from eva_engine.render.sh import SH_C0


@torch.no_grad()
def lid_colours(folder: str) -> dict:
    avatar = load_avatar(folder)
    g = avatar.gaussians
    reach = avatar.expression_reach[g.vertex_ids]  # [N, K]
    sh0, offsets = g.splats["sh0"][:, 0], g.splats["sh0_expression"]
    names = [avatar.body.expression_names[i] for i in avatar.expression_actions.tolist()]
    out = {}
    for k, name in enumerate(names):
        m = reach[:, k]
        rest, closed = SH_C0 * sh0[m] + 0.5, SH_C0 * (sh0[m] + offsets[m, k]) + 0.5
        _, inv, count = torch.unique(g.vertex_ids[m], return_inverse=True, return_counts=True)
        mean = torch.zeros(len(count), 3).index_add_(0, inv, closed) / count[:, None]
        within = (closed - mean[inv]).norm(dim=-1)
        out[name] = {
            "range": float(avatar.expression_range[k]),
            "gaussians": int(m.sum()),
            "vertices": len(count),
            "gaussians_per_vertex_median": float(count.float().median()),
            "rest_rgb_mean": [round(x, 3) for x in rest.mean(0).tolist()],
            "closed_rgb_mean": [round(x, 3) for x in closed.mean(0).tolist()],
            "closed_rgb_std_norm": round(float(closed.std(0).norm()), 3),
            "closed_within_vertex_deviation_median": round(float(within.median()), 3),
            "closed_between_vertex_std_norm": round(float(mean.std(0).norm()), 3),
            "closed_outside_0_1_share": round(float(((closed < 0) | (closed > 1)).any(-1).float().mean()), 3),
            "opacity_mean": round(float(g.opacities()[m].mean()), 3),
        }
    return out


if __name__ == "__main__":
    result = {folder: lid_colours(folder) for folder in sys.argv[2:]}
    with open(sys.argv[1], "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps(result, indent=1))
