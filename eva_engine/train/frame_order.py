"""``FrameOrder``: which training frame each step sees.

Uniform (``strength = 0``): a seeded random permutation, epoch by epoch, as 3DGS and EVA do.
Expression-weighted (``strength > 0``): each epoch draws as many frames, with replacement, with
probability proportional to ``1 + strength * rarity``. A frame's rarity is, for each group of
facial actions (jaw, lips, lids, brows: ``body.EXPRESSION_GROUPS``), the distance of its fitted
actions from the clip's median ones over the mean such distance, and then the largest over the
groups: a blink is rare among the lids even in a clip whose mouth never rests. A face spends most
frames near one expression; a blink lasts a few frames, and a uniform order shows the closed lids
as rarely as the video does, too rarely for the Gaussians of the lids to learn how they look
closed (``docs/alignment.md``).
"""

from __future__ import annotations

import torch
from torch import Tensor


def expression_rarity(expression: Tensor, groups: list[Tensor] | None = None) -> Tensor:
    """[N] each frame's rarity in ``expression [N, E]``: per group of actions (``groups``, [E]
    bool masks; None: all actions as one), its distance from the median over the mean distance
    (0 for a group in which every frame is the same), the largest over the groups."""
    groups = [torch.ones(expression.shape[1], dtype=torch.bool)] if groups is None else groups
    rarity = torch.zeros(expression.shape[0], dtype=expression.dtype)
    for mask in groups:
        part = expression[:, mask]
        distance = (part - part.median(dim=0).values).norm(dim=-1)
        mean = distance.mean()
        if part.shape[1] and mean > 1e-9:
            rarity = torch.maximum(rarity, distance / mean)
    return rarity


class FrameOrder:
    """Frame indices, one per step, from a generator of its own (seeded by the caller).

    expression: [N, E] the training frames' fitted expressions (only read when ``strength > 0``);
    groups: [E] bool masks of its groups of actions (``body.expression_group_masks``).
    """

    def __init__(
        self,
        expression: Tensor,
        strength: float,
        generator: torch.Generator,
        groups: list[Tensor] | None = None,
    ) -> None:
        if not 0.0 <= strength <= 100.0:
            raise ValueError(f"expression sampling strength must be in [0, 100], got {strength}")
        self.count = expression.shape[0]
        self.generator = generator
        self.weights = None
        if strength > 0:
            self.weights = 1.0 + strength * expression_rarity(expression.detach().double().cpu(), groups)
        self._epoch: list[int] = []

    @property
    def probabilities(self) -> Tensor:
        """[N] the chance of each frame at a step."""
        if self.weights is None:
            return torch.full((self.count,), 1.0 / self.count, dtype=torch.float64)
        return self.weights / self.weights.sum()

    def next(self) -> int:
        if not self._epoch:
            if self.weights is None:
                self._epoch = torch.randperm(self.count, generator=self.generator).tolist()
            else:
                draws = torch.multinomial(
                    self.weights, self.count, replacement=True, generator=self.generator
                )
                self._epoch = draws.tolist()
        return self._epoch.pop()
