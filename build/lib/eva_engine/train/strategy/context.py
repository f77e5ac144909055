"""``ContextAwareStrategy``: EVA's context-aware adaptive density control (paper §3.3).

``DefaultStrategy`` with two of its hooks changed; everything else (gradient accumulation,
clone/split/prune, the window schedule) is the baseline's.

**Densification thresholds** (``densify_thresholds``) depend on the Gaussian's part (body, hand,
face: ``avatar.gaussians.part_ids``) and on its gradient history. With R = ``refine_every`` (the
densification interval) and ∇_{i,k} the screen-space gradient norm of Gaussian i at step k (3DGS
units, as ``DefaultStrategy`` accumulates it):

    ε_i = e_part + (λ_part / R) (Σ_{k=t-R..t} ∇_{i,k} - Σ_{k=t-2R..t-R} ∇_{i,k})        (paper eq. 8)

with e = 2e-4 / 1e-4 / 1.4e-4 and λ = -9.0 / -4.5 / -6.3 for body / hand / face (appendix): a
Gaussian whose gradient keeps rising gets a lower threshold and densifies sooner. Choices:

- ``history="per_gaussian"`` (the paper): each window sum is taken over the steps the Gaussian
  was visible and divided by that count instead of R, i.e. ε_i = e + λ (ḡ_i,now − ḡ_i,prev) with ḡ
  the window's mean gradient. This equals the formula when the Gaussian is visible in every step
  and does not mistake "seen in fewer frames" for "gradient fell". A Gaussian not seen in both
  windows has no history term (ε_i = e_part).
- ``history="part_mean"`` (the official code, ``scene/gaussian_model.py``): one threshold per part
  from the part's mean of ḡ in the current window minus that of the previous one. The official
  code writes it as w_part (τ + λ Δ_part) with w = 1.0 / 0.5 / 0.7, τ = 2e-4, λ = -9: the paper's
  e and λ above are exactly w·τ and w·λ, so both forms share ``part_grad_base`` and
  ``part_grad_lambda``.
- ``history="official"``: the official code's densification as it runs, which differs from
  ``part_mean`` in four ways (``densify_and_clone`` / ``densify_and_split`` /
  ``densify_and_prune``):
  1. ḡ is a part's mean over *all* its Gaussians of the mean gradient since the last event,
     unseen ones counted as 0 (its ``grads[grads.isnan()] = 0``), and the previous value is that
     of the Gaussians the part had at the last event, before it densified.
  2. At the first event there is no history: ``prev = 0`` and Δ is the mean over every Gaussian
     of every part, so the thresholds fall by λ times the whole mean gradient and the first
     event densifies in a burst.
  3. λ applies to splits only (``lamda_clone_pos_grad = 0``): clones use e_part. The split's
     part mean is taken after the clones are appended, and they count as zeros in it.
  4. No floor: a threshold may go below 0 (every split-sized Gaussian of the part splits).
  The accumulators run from step 0 to the first event, then over each interval, as 3DGS's.
- Windows: the last two windows of R steps ending at the refinement step are tracked (from step
  0, so the first refinement at ``refine_start_iter`` >= 2R already has a previous window).
- λ is large against e (a change of 2.2e-5 in the mean gradient of a body Gaussian moves its
  threshold to 0), so thresholds are floored at ``min_threshold_ratio`` · e_part: a threshold
  <= 0 would densify every Gaussian, unseen ones included.
- Clones and splits inherit the part id (``ops``) and the parent's gradient history: ``ops`` gives
  new rows of the strategy state zeros, so ``refine`` restores the parent's history afterwards —
  exactly for clones (they sit on their parent), and for split children from the nearest
  pre-refinement Gaussian of the same part (children are drawn within the parent's footprint).

**Pruning** (``prune_distance_thresholds``): by canonical distance to the nearest template vertex
*of the Gaussian's own part* with per-part limits (official code: body 0.03, hand 0.05, face
0.09 m); ``part_prune_dist=None`` keeps the baseline's single distance to any part.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.avatar.gaussians import CanonicalGaussians
from eva_engine.body.model import PART_NAMES, nearest_vertex_index
from eva_engine.render import RenderOutput
from eva_engine.train.strategy.default import DefaultStrategy
from eva_engine.train.strategy.ops import Optimizers

HISTORY_FORMS = ("per_gaussian", "part_mean", "official")


@dataclass
class ContextAwareStrategy(DefaultStrategy):
    """EVA's density control (see the module docstring). Per-part tuples follow ``PART_NAMES``
    (body, hand, face).

    part_grad_base: e per part (the threshold without history).
    part_grad_lambda: λ per part (negative: a rising gradient lowers the threshold).
    history: "per_gaussian" (paper eq. 8), "part_mean" (the official code's part means on the
        project's windows) or "official" (the official code's densification exactly).
    min_threshold_ratio: floor of the threshold as a fraction of e_part ("official": none).
    part_prune_dist: same-part template distance limits (metres); None: the baseline's
        ``prune_template_dist`` to any part.
    """

    part_grad_base: tuple[float, float, float] = (2e-4, 1e-4, 1.4e-4)
    part_grad_lambda: tuple[float, float, float] = (-9.0, -4.5, -6.3)
    history: str = "per_gaussian"
    min_threshold_ratio: float = 0.25
    part_prune_dist: tuple[float, float, float] | None = (0.03, 0.05, 0.09)

    def __post_init__(self) -> None:
        if self.history not in HISTORY_FORMS:
            raise ValueError(f"history must be one of {HISTORY_FORMS}, got {self.history!r}")
        for name in ("part_grad_base", "part_grad_lambda", "part_prune_dist"):
            value = getattr(self, name)
            if value is not None and len(value) != len(PART_NAMES):
                raise ValueError(f"{name} needs one value per part {PART_NAMES}, got {value}")

    def initialize_state(self) -> dict:
        state = super().initialize_state()
        state.update(
            win_sum=None,  # [N] gradient norms summed over the current window's visible steps
            win_count=None,  # [N] visible steps in the current window
            prev_mean=None,  # [N] mean gradient of the previous window
            prev_seen=None,  # [N] 1 where the previous window saw the Gaussian
            part_prev=None,  # "official": ḡ per part at the last event (None before the first)
        )
        return state

    # -- statistics ----------------------------------------------------------------------------
    @torch.no_grad()
    def update_state(self, gaussians: CanonicalGaussians, state: dict, render: RenderOutput) -> None:
        n = len(gaussians)
        if state["win_sum"] is None or state["win_sum"].shape[0] != n:
            for key in ("win_sum", "win_count", "prev_mean", "prev_seen"):
                state[key] = torch.zeros(n, device=gaussians.means.device)
        aligned = state["grad2d"] is not None and state["grad2d"].shape[0] == n
        before = (state["grad2d"].clone(), state["count"].clone()) if aligned else None
        super().update_state(gaussians, state, render)
        # This step's contribution, as the baseline measured it.
        state["win_sum"] += state["grad2d"] - (before[0] if before else 0.0)
        state["win_count"] += state["count"] - (before[1] if before else 0.0)

    @staticmethod
    def window_mean(state: dict) -> tuple[Tensor, Tensor]:
        """([N] mean gradient of the current window, [N] bool seen in it)."""
        count = state["win_count"]
        return state["win_sum"] / count.clamp_min(1), count > 0

    @staticmethod
    def roll_window(state: dict, cur_mean: Tensor, cur_seen: Tensor) -> None:
        """The current window becomes the previous one (rows as given); a new one starts."""
        state["prev_mean"] = cur_mean.clone()
        state["prev_seen"] = cur_seen.to(cur_mean.dtype)
        state["win_sum"] = torch.zeros_like(cur_mean)
        state["win_count"] = torch.zeros_like(cur_mean)

    # -- hooks ---------------------------------------------------------------------------------
    def _per_part(self, values: tuple[float, ...], gaussians: CanonicalGaussians) -> Tensor:
        return torch.tensor(values, device=gaussians.means.device)[gaussians.part_ids]

    def history_delta(self, state: dict, gaussians: CanonicalGaussians) -> Tensor:
        """[N] mean-gradient change between the previous and the current window (0 where there
        is no history), per Gaussian or per part (``history``)."""
        cur, seen_cur = self.window_mean(state)
        prev, seen_prev = state["prev_mean"], state["prev_seen"] > 0
        if self.history == "per_gaussian":
            return torch.where(seen_cur & seen_prev, cur - prev, torch.zeros_like(cur))
        delta = torch.zeros_like(cur)
        for part in range(len(PART_NAMES)):
            in_part = gaussians.part_ids == part
            now, before = in_part & seen_cur, in_part & seen_prev
            if bool(now.any()) and bool(before.any()):
                delta[in_part] = cur[now].mean() - prev[before].mean()
        return delta

    def official_thresholds(self, state: dict, gaussians: CanonicalGaussians) -> Tensor:
        """[N] the official code's thresholds (module docstring, ``history="official"``): e_part
        for clone-sized Gaussians, e_part + λ_part Δ_part for split-sized ones (``refine`` keeps
        this event's ḡ per part, from its per-part report, as the next one's history)."""
        grads = state["grad2d"] / state["count"].clamp_min(1)  # unseen: 0
        parts = gaussians.part_ids
        e = self._per_part(self.part_grad_base, gaussians)
        lam = self._per_part(self.part_grad_lambda, gaussians)
        small = gaussians.scales().amax(dim=-1) <= self.grow_scale3d
        in_part = [parts == p for p in range(len(PART_NAMES))]
        if state["part_prev"] is None:
            delta = grads.mean().expand_as(grads)
        else:
            clones = small & (grads > e)
            delta = torch.zeros_like(grads)
            for p, sel in enumerate(in_part):
                n = int(sel.sum()) + int((clones & sel).sum())
                if n:
                    delta[sel] = grads[sel].sum() / n - state["part_prev"][p]
        return torch.where(small, e, e + lam * delta)

    def densify_thresholds(self, state: dict, gaussians: CanonicalGaussians) -> Tensor:
        """[N] ε_i = max(e_part + λ_part Δ_i, min_threshold_ratio e_part); "official": its own
        (``official_thresholds``)."""
        if self.history == "official":
            return self.official_thresholds(state, gaussians)
        e = self._per_part(self.part_grad_base, gaussians)
        lam = self._per_part(self.part_grad_lambda, gaussians)
        eps = e + lam * self.history_delta(state, gaussians)
        return torch.maximum(eps, self.min_threshold_ratio * e)

    def prune_distance_thresholds(self, gaussians: CanonicalGaussians) -> tuple[Tensor, bool]:
        if self.part_prune_dist is None:
            return super().prune_distance_thresholds(gaussians)
        return self._per_part(self.part_prune_dist, gaussians), True

    # -- the step ------------------------------------------------------------------------------
    def step_post_backward(
        self,
        gaussians: CanonicalGaussians,
        optimizers: Optimizers,
        state: dict,
        step: int,
        render: RenderOutput,
    ) -> dict[str, int]:
        stats = super().step_post_backward(gaussians, optimizers, state, step, render)
        # Window boundaries before densification starts (``refine`` rolls at the others).
        if 0 < step < min(self.refine_start_iter, self.refine_stop_iter) and step % self.refine_every == 0:
            self.roll_window(state, *self.window_mean(state))
        return stats

    @torch.no_grad()
    def refine(self, gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict) -> dict[str, int]:
        """The baseline's refinement, then the window roll with the history inherited."""
        n = len(gaussians)
        cur, seen = self.window_mean(state)
        means, parts = gaussians.means.detach().clone(), gaussians.part_ids.clone()
        # Row i of the pre-refinement set is i + 1 here; ops keep it on survivors, 0 on new rows.
        state["origin"] = torch.arange(1, n + 1, device=means.device)
        stats = super().refine(gaussians, optimizers, state)
        parent = self.parents(gaussians, state.pop("origin"), means, parts)
        self.roll_window(state, cur[parent], seen[parent])
        if self.history == "official":  # ḡ per part before densifying, unseen Gaussians as 0
            state["part_prev"] = [stats["parts"].get(name, {}).get("g_mean", 0.0) for name in PART_NAMES]
        return stats

    @staticmethod
    def parents(gaussians: CanonicalGaussians, origin: Tensor, means: Tensor, parts: Tensor) -> Tensor:
        """[N] pre-refinement row of each Gaussian: its own for survivors (``origin`` > 0), for
        new ones the nearest pre-refinement Gaussian of the same part. means, parts: [M, 3], [M]
        of the pre-refinement set."""
        parent = origin - 1
        new = parent < 0
        if bool(new.any()):
            cur_means = gaussians.means.detach()
            for part in gaussians.part_ids[new].unique().tolist():
                sel = new & (gaussians.part_ids == part)
                pool = torch.nonzero(parts == part).squeeze(1)
                if pool.numel() == 0:  # cannot happen (children keep the part); any row then
                    pool = torch.arange(means.shape[0], device=means.device)
                parent[sel] = pool[nearest_vertex_index(cur_means[sel], means[pool])]
        return parent
