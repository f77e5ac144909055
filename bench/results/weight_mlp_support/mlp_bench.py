"""The weight MLP's forward + backward with every output (dense) against only each chunk's bones
(``bone_plan.patch`` applied: ``BonePlan``, ``relu_mlp(..., plan=)``): the weights' and
gradients' differences, then the median of 6 timed calls, alternating.
``python mlp_bench.py <threads> <Gaussians> <MLP width>``."""

import sys
import time

import torch

from eva_engine.avatar.networks import BonePlan, LBSWeightOffsets, positional_encoding, relu_mlp
from eva_engine.body import load_body_model

torch.set_num_threads(int(sys.argv[1]))
n, width = int(sys.argv[2]), int(sys.argv[3])
weights = load_body_model("anny").skinning_weights
vertices, bones = weights.shape
log_base, support = torch.log(weights + 1e-8), weights > 0
generator = torch.Generator().manual_seed(0)
rows = torch.randint(0, vertices, (n,), generator=generator)
means = (torch.randn(n, 3, generator=generator) * 0.3).requires_grad_(True)
net = LBSWeightOffsets(bones, 6, width, 2, 0.3)  # a large last-layer init: offsets far from 0
ramp = torch.linspace(0, 1, bones)


def run(plan):
    for p in net.parameters():
        p.grad = None
    means.grad = None
    out = relu_mlp(positional_encoding(means, 6), net.mlp, log_prior=(log_base, rows), plan=plan)
    (out * ramp).sum().backward()
    return out.detach(), [p.grad.clone() for p in net.parameters()], means.grad.clone()


plan = BonePlan(rows, support)
dense, planned = run(None), run(plan)
rel = max(float((a - b).norm() / a.norm()) for a, b in zip(dense[1], planned[1], strict=True))
rel_means = float((dense[2] - planned[2]).norm() / dense[2].norm())
print(
    f"largest weight difference {float((dense[0] - planned[0]).abs().max()):.1e}; "
    f"parameter gradients {rel:.1e} and means' {rel_means:.1e} relative"
)
for name, p in (("dense", None), ("bones", plan)) * 2:
    times = []
    for _ in range(6):
        start = time.perf_counter()
        run(p)
        times.append(time.perf_counter() - start)
    print(f"{name}: {sorted(times)[3] * 1e3:.1f} ms")
