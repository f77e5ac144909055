"""Stand-ins for what a density-control strategy reads from a training step."""

from __future__ import annotations

import torch

from eva_engine.render import RenderOutput


def render_with_grad(grad: torch.Tensor, visible: torch.Tensor | None = None) -> RenderOutput:
    """A render whose screen-space gradient is ``grad [N]`` (x only; a 2x2 image makes the NDC
    scaling 1)."""
    n = grad.shape[0]
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = torch.stack([grad, torch.zeros_like(grad)], dim=-1)
    radii = torch.ones(n, dtype=torch.int32) if visible is None else visible.to(torch.int32)
    return RenderOutput(
        torch.zeros(2, 2, 3), torch.zeros(2, 2, 1), torch.zeros(2, 2, 1), means2d, radii, torch.ones(n), 0
    )
