"""The density-control interface (gsplat-style: a config dataclass with explicit state).

A trainer holds ``strategy`` and ``state = strategy.initialize_state()`` and calls, per step,
``strategy.step_post_backward(gaussians, optimizers, state, step, render)`` after the backward
pass and optimizer step (``render.means2d.grad`` then holds the screen-space gradient), and
``strategy.finalize(gaussians, optimizers, state)`` once after the last step. A step that also
renders a second view of its frame (a face close-up) may pass it to ``strategy.observe_view``
first, so that its screen-space gradients count toward density control. The
strategy may add, split or remove Gaussians; it does so only through ``strategy.ops``, which
keep splats, optimizer state, per-Gaussian buffers and every per-Gaussian tensor of ``state``
aligned. All mutable data lives in ``state``; the strategy object itself is configuration.
"""

from __future__ import annotations

from dataclasses import dataclass

from eva_engine.avatar.gaussians import CanonicalGaussians
from eva_engine.render import RenderOutput
from eva_engine.train.strategy.ops import Optimizers


@dataclass
class Strategy:
    """Base class: no density control at all (a fixed set of Gaussians)."""

    def initialize_state(self) -> dict:
        return {}

    def check_sanity(self, gaussians: CanonicalGaussians, optimizers: Optimizers) -> None:
        """Every optimizer named after a splat must optimise exactly that tensor."""
        for name, opt in optimizers.items():
            if name not in gaussians.splats:
                raise ValueError(f"optimizer {name!r} has no matching splat")
            params = opt.param_groups[0]["params"]
            if len(opt.param_groups) != 1 or len(params) != 1 or params[0] is not gaussians.splats[name]:
                raise ValueError(f"optimizer {name!r} must hold exactly splats[{name!r}]")

    def observe_view(
        self, gaussians: CanonicalGaussians, state: dict, step: int, render: RenderOutput
    ) -> None:
        """Another render of this step's frame, after the backward pass and before
        ``step_post_backward``: its statistics count like a view of their own."""

    def step_post_backward(
        self,
        gaussians: CanonicalGaussians,
        optimizers: Optimizers,
        state: dict,
        step: int,
        render: RenderOutput,
    ) -> dict[str, int]:
        """Update statistics and maybe refine; returns counts of what changed (may be empty)."""
        return {}

    def finalize(self, gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict) -> dict:
        """Called once after the last step; may remove Gaussians (through ``ops``). Returns what
        changed (may be empty)."""
        return {}
