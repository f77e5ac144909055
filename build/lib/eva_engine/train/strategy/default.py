"""``DefaultStrategy``: 3DGS adaptive density control, plus pruning by distance to the body
template (GauHuman / EVA). The "3DGS + body" baseline of the paper.

Every step: the screen-space gradient norm of each visible Gaussian's centre, in 3DGS units
(dL/dmeans2d in pixels scaled by (W/2, H/2), i.e. per normalised device coordinate), is
accumulated in ``state["grad2d"]`` with a visibility count ``state["count"]``. Every
``refine_every`` steps in [refine_start_iter, refine_stop_iter): Gaussians whose mean gradient
exceeds their threshold (``densify_thresholds``; here the constant ``grow_grad2d``) are cloned
when small (max scale <= ``grow_scale3d``) or split when large; then Gaussians with opacity below
``prune_opa``, scale above ``prune_scale3d``, or canonical distance to the template above
``prune_distance_thresholds`` are removed, and the accumulators reset (``end_window``).

**Parts never seen** (``prune_unseen_parts``; "model only what a scene needs"): every step
records which parts (body, hand, face) had a Gaussian that reached the image, i.e. was on screen
and received a non-zero screen-space gradient (off-screen and fully occluded Gaussians get
none). After the last step (``finalize``), the Gaussians of a part that was never seen are
removed: a video that never shows the hands must not spend Gaussians on untrained hands. This
is decided at the end, not at a refinement, because a part may first appear late in the frame
order.

**A final prune** (``prune_extent``, ``prune_never_seen``; off by default, as 3DGS): after the last
step, Gaussians whose 3-sigma ellipsoid reaches farther than ``prune_extent`` from the template
(centre distance + 3 x largest standard deviation) go, and so do Gaussians that no step ever
saw (no screen-space gradient in any training frame: hidden or off-screen in all of them, so
nothing fitted their colour or opacity). Pruning during training looks at the centre alone and
stops at ``refine_stop_iter``; a Gaussian may grow for the rest of the run.

Subclasses change the policy through the three hooks (``densify_thresholds``,
``prune_distance_thresholds``, ``end_window``) and extra per-Gaussian entries in ``state``, which
the ops keep aligned; e.g. the context-aware strategy keeps the previous window's gradient
sums and sets per-part thresholds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Self

import torch
from torch import Tensor

import eva_engine.train.strategy.ops as ops
from eva_engine.avatar.gaussians import CanonicalGaussians
from eva_engine.body.model import PART_NAMES
from eva_engine.render import RenderOutput
from eva_engine.train.strategy.base import Strategy
from eva_engine.train.strategy.ops import Optimizers


@dataclass
class DefaultStrategy(Strategy):
    """3DGS density control (see the module docstring). Lengths are metres of canonical space.

    grow_grad2d: densification threshold on the mean NDC gradient norm (3DGS: 2e-4).
    grow_scale3d: clone below / split above this max scale (3DGS: 0.01 of the scene extent; a
        human is ~1 m).
    prune_opa: remove below this opacity (3DGS: 0.005).
    prune_scale3d: remove above this max scale (3DGS: 0.1 of the extent).
    prune_template_dist: remove Gaussians farther than this from every template vertex.
    refine_start_iter, refine_stop_iter, refine_every: the densification window (EVA: 400, 1000,
        100).
    reset_every: opacity reset period (3DGS: 3000; longer than EVA's 2,000 iterations, so off).
    max_gaussians: optional budget: above it, only the candidates furthest above their
        threshold (gradient / threshold) are densified.
    prune_unseen_parts: remove, after training, the Gaussians of parts no step ever saw.
    prune_extent: after training, remove Gaussians whose 3-sigma extent reaches farther than this
        from the template (None: off).
    prune_never_seen: after training, remove Gaussians that no step saw.
    seed: for the split samples.
    """

    grow_grad2d: float = 2e-4
    grow_scale3d: float = 0.01
    prune_opa: float = 0.005
    prune_scale3d: float = 0.1
    prune_template_dist: float = 0.05
    refine_start_iter: int = 400
    refine_stop_iter: int = 1000
    refine_every: int = 100
    reset_every: int = 3000
    max_gaussians: int | None = None
    prune_unseen_parts: bool = True
    prune_extent: float | None = None
    prune_never_seen: bool = False
    seed: int = 0

    @classmethod
    def from_default(cls, base: DefaultStrategy, **overrides) -> Self:
        """This strategy with ``base``'s schedule and 3DGS settings (a subclass's own fields at
        their defaults unless in ``overrides``)."""
        fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(DefaultStrategy)}
        return cls(**{**fields, **overrides})

    def initialize_state(self) -> dict:
        return {
            "grad2d": None,  # [N] summed gradient norms of the current window
            "count": None,  # [N] steps each Gaussian was visible in the window
            "seen": None,  # [N] steps in which each Gaussian received a gradient (whole run)
            # Steps in which each part was seen: a list (not a per-Gaussian tensor the ops edit).
            "part_seen": [0] * len(PART_NAMES),
            "generator": torch.Generator().manual_seed(self.seed),
        }

    # -- hooks -----------------------------------------------------------------------------
    def densify_thresholds(self, state: dict, gaussians: CanonicalGaussians) -> Tensor:
        """[N] (or scalar) gradient threshold per Gaussian."""
        return torch.tensor(self.grow_grad2d, device=gaussians.means.device)

    def prune_distance_thresholds(self, gaussians: CanonicalGaussians) -> tuple[Tensor, bool]:
        """([N] or scalar max distance to the template, whether to measure to the same part)."""
        return torch.tensor(self.prune_template_dist, device=gaussians.means.device), False

    def end_window(self, state: dict) -> None:
        """Reset the accumulators after a refinement."""
        state["grad2d"].zero_()
        state["count"].zero_()

    # -- the step ----------------------------------------------------------------------------
    @staticmethod
    @torch.no_grad()
    def record_seen_parts(gaussians: CanonicalGaussians, state: dict, render: RenderOutput) -> None:
        """Count this step for every part with a Gaussian on screen and a non-zero gradient."""
        grad = render.means2d.grad
        if grad is None:
            return
        reached = (render.radii > 0) & (grad.abs().amax(dim=-1) > 0)
        seen = torch.bincount(gaussians.part_ids[reached], minlength=len(PART_NAMES))
        for part, n in enumerate(seen.tolist()[: len(PART_NAMES)]):
            state["part_seen"][part] += int(n > 0)
        if state.get("seen") is None or state["seen"].shape[0] != len(gaussians):
            state["seen"] = torch.zeros(len(gaussians), device=gaussians.means.device)
        state["seen"] += reached.to(state["seen"])

    @torch.no_grad()
    def update_state(self, gaussians: CanonicalGaussians, state: dict, render: RenderOutput) -> None:
        n = len(gaussians)
        device = gaussians.means.device
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, device=device)
            state["count"] = torch.zeros(n, device=device)
        grad = render.means2d.grad
        if grad is None:
            return
        h, w = render.image.shape[:2]
        grad = grad * grad.new_tensor([w / 2.0, h / 2.0])
        visible = render.radii > 0
        state["grad2d"][visible] += grad[visible].norm(dim=-1)
        state["count"][visible] += 1

    def observe_view(
        self, gaussians: CanonicalGaussians, state: dict, step: int, render: RenderOutput
    ) -> None:
        """A second view's gradients join the window's, each Gaussian visible in it counted once
        more (as 3DGS averages over the views of a scene)."""
        if step < self.refine_stop_iter:
            self.update_state(gaussians, state, render)

    def step_post_backward(
        self,
        gaussians: CanonicalGaussians,
        optimizers: Optimizers,
        state: dict,
        step: int,
        render: RenderOutput,
    ) -> dict[str, int]:
        self.record_seen_parts(gaussians, state, render)
        if step >= self.refine_stop_iter:
            return {}
        self.update_state(gaussians, state, render)
        stats: dict[str, int] = {}
        if step >= self.refine_start_iter and step % self.refine_every == 0 and step > 0:
            stats = self.refine(gaussians, optimizers, state)
        if self.reset_every > 0 and step > 0 and step % self.reset_every == 0:
            ops.reset_opacity(gaussians, optimizers, state, 2.0 * self.prune_opa)
        return stats

    @torch.no_grad()
    def refine(self, gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict) -> dict[str, int]:
        """Densify then prune (see the module docstring); returns the counts."""
        grads = state["grad2d"] / state["count"].clamp_min(1)
        thresholds = self.densify_thresholds(state, gaussians)
        candidates = grads > thresholds
        if self.max_gaussians is not None:
            room = max(self.max_gaussians - len(gaussians), 0)
            if int(candidates.sum()) > room:
                # Strongest first, relative to each Gaussian's own threshold.
                excess = grads / thresholds.clamp_min(1e-12)
                order = torch.argsort(torch.where(candidates, excess, -1.0), descending=True)
                candidates = torch.zeros_like(candidates)
                candidates[order[:room]] = True
        small = gaussians.scales().amax(dim=-1) <= self.grow_scale3d
        is_clone, is_split = candidates & small, candidates & ~small
        n_clone, n_split = int(is_clone.sum()), int(is_split.sum())
        parts = self.part_report(gaussians.part_ids, grads, thresholds, small, is_clone, is_split)
        if n_clone:
            ops.duplicate(gaussians, optimizers, state, is_clone)
            is_split = torch.cat([is_split, is_split.new_zeros(n_clone)])
        if n_split:
            ops.split(gaussians, optimizers, state, is_split, generator=state["generator"])
        n_prune = self.prune(gaussians, optimizers, state)
        gaussians.refresh_vertex_ids()
        self.end_window(state)
        return {
            "cloned": n_clone,
            "split": n_split,
            "pruned": n_prune,
            "gaussians": len(gaussians),
            "parts": parts,
        }

    @staticmethod
    def part_report(
        part_ids: Tensor, grads: Tensor, thresholds: Tensor, small: Tensor, is_clone: Tensor, is_split: Tensor
    ) -> dict[str, dict[str, float]]:
        """What a refinement did per part: its Gaussians ``n``, their mean gradient ``g_mean``
        (unseen ones as 0), the mean threshold of the clone-sized (``eps_clone``) and split-sized
        (``eps_split``) ones (None when there are none), and how many were cloned and split.
        All inputs [N] (``thresholds`` may be a scalar)."""
        thresholds = thresholds.expand_as(grads)
        out = {}
        for part, name in enumerate(PART_NAMES):
            sel = part_ids == part
            if not bool(sel.any()):
                continue

            def mean(values: Tensor) -> float | None:
                return float(values.mean()) if values.numel() else None

            out[name] = {
                "n": int(sel.sum()),
                "g_mean": float(grads[sel].mean()),
                "eps_clone": mean(thresholds[sel & small]),
                "eps_split": mean(thresholds[sel & ~small]),
                "cloned": int((is_clone & sel).sum()),
                "split": int((is_split & sel).sum()),
            }
        return out

    @torch.no_grad()
    def prune(self, gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict) -> int:
        """Remove Gaussians below ``prune_opa`` opacity, above ``prune_scale3d`` or too far from
        the template (``prune_distance_thresholds``), never all of them; returns how many."""
        dist_max, same_part = self.prune_distance_thresholds(gaussians)
        dist = gaussians.template_distance(same_part=same_part)
        prune = (
            (gaussians.opacities() < self.prune_opa)
            | (gaussians.scales().amax(dim=-1) > self.prune_scale3d)
            | (dist > dist_max)
        )
        prune &= ~torch.all(prune)  # never remove everything
        n_prune = int(prune.sum())
        if n_prune:
            ops.remove(gaussians, optimizers, state, prune)
        return n_prune

    @torch.no_grad()
    def finalize(self, gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict) -> dict:
        """After the last step: remove the Gaussians of parts never seen (``prune_unseen_parts``),
        then the final prune (``prune_extent``, ``prune_never_seen``); returns what it did (empty
        when nothing changed). Never removes every Gaussian."""
        out: dict = {}
        unseen = [p for p, n in enumerate(state.get("part_seen", [])) if n == 0]
        if self.prune_unseen_parts and unseen:
            drop = torch.isin(gaussians.part_ids, torch.tensor(unseen, device=gaussians.part_ids.device))
            if bool(drop.any()) and not bool(drop.all()):  # nothing seen at all, or nothing to drop
                ops.remove(gaussians, optimizers, state, drop)
                out |= {"unseen_parts": [PART_NAMES[p] for p in unseen], "pruned": int(drop.sum())}
        drop = torch.zeros(len(gaussians), dtype=torch.bool, device=gaussians.means.device)
        if self.prune_extent is not None:
            reach = gaussians.template_distance() + 3.0 * gaussians.scales().amax(dim=-1)
            drop |= reach > self.prune_extent
        if self.prune_never_seen and state.get("seen") is not None and len(state["seen"]) == len(drop):
            drop |= state["seen"] == 0
        if bool(drop.any()) and not bool(drop.all()):
            out["pruned_final"] = int(drop.sum())
            ops.remove(gaussians, optimizers, state, drop)
        if out:
            gaussians.refresh_vertex_ids()
            out["gaussians"] = len(gaussians)
        return out
