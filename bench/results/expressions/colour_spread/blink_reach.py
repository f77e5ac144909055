"""What each blink recolours, by Anny's mesh pieces, without and with the spread; and how far
each piece moves with the blink, as a share of the lid's largest displacement (``README.md``).

    python bench/results/expressions/colour_spread/blink_reach.py > blink_reach.md
"""

from __future__ import annotations

import torch

from eva_engine.avatar.config import BLINK_ACTIONS
from eva_engine.avatar.expression_colours import action_reach, revealing_actions
from eva_engine.body import load_body_model
from eva_engine.body.anny_backend import SEGMENT_LABELS

SPREAD = 0.006


def main() -> None:
    body = load_body_model("anny")
    names = list(body.expression_names)
    labels = torch.as_tensor(body.segment_labels)
    actions = revealing_actions(names, BLINK_ACTIONS)
    plain = action_reach(body, body.shape_defaults, actions)
    spread = action_reach(body, body.shape_defaults, actions, spread=SPREAD)
    params = body.default_params(len(actions) + 1)
    for row, a in enumerate(actions, start=1):
        params.expression[row, a] = 1.0
    with torch.no_grad():
        rest = body.canonical(params)
    print("# What a blink recolours (Anny, default shape)\n")
    print(
        f"Vertices reached, by mesh piece: the blink's colour reach alone and with a {SPREAD * 1000:.0f} mm"
    )
    print("spread (local); and each piece's largest displacement under the blink at 1 over the lid's.\n")
    print("| blink | piece | reached, no spread | reached, spread | displacement / lid's |")
    print("|---|---|---:|---:|---:|")
    for k, a in enumerate(actions):
        moved = (rest[k + 1] - rest[0]).norm(dim=-1)
        for i, piece in enumerate(SEGMENT_LABELS):
            sel = labels == i
            n0, n1 = int(plain[sel, k].sum()), int(spread[sel, k].sum())
            share = float(moved[sel].max() / moved.max())
            if n0 or n1:
                print(f"| {names[a]} | {piece} | {n0} | {n1} | {share:.2f} |")
        print(f"| {names[a]} | all | {int(plain[:, k].sum())} | {int(spread[:, k].sum())} | |")


if __name__ == "__main__":
    main()
