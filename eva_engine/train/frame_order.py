"""The order training visits its frames in: each frame once per epoch, shuffled, and optionally the
frames of a rare expression more often.

A blink lasts a few frames of a clip: on the gesturing LatentSync clip 13 of 225 training frames
have a fitted eyeBlink above 0.2, so a 600-step run shows the avatar a closed eye about 35
times, against thousands for the open one, and what the blink's colour offsets learn from so
few steps is noisy (issue 39). ``ExpressionEventsConfig`` repeats each frame whose fitted
coefficient of one of ``actions`` passes ``threshold`` ``repeats`` more times per epoch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from eva_engine.avatar.config import BLINK_ACTIONS


@dataclass(frozen=True)
class ExpressionEventsConfig:
    """repeats: extra visits per epoch of each frame with an event (0: every frame once, as
    without this option); actions: the facial actions whose frames count (by the body model's
    names; those it lacks are ignored); threshold: a frame has an event where one of their fitted
    coefficients exceeds it."""

    repeats: int = 0
    actions: tuple[str, ...] = BLINK_ACTIONS
    threshold: float = 0.2

    def __post_init__(self) -> None:
        if self.repeats < 0:
            raise ValueError(f"repeats must be >= 0, got {self.repeats}")


def epoch_frames(expression: Tensor, names: list[str], config: ExpressionEventsConfig) -> list[int]:
    """One epoch's frames (unshuffled): every index of ``expression`` [F, E] once, then the frames
    with an event ``config.repeats`` times more."""
    frames = list(range(expression.shape[0]))
    columns = [names.index(a) for a in config.actions if a in names]
    if config.repeats == 0 or not columns:
        return frames
    events = (expression[:, columns] > config.threshold).any(dim=1).nonzero().flatten().tolist()
    return frames + events * config.repeats


def shuffled(frames: list[int], generator: torch.Generator) -> list[int]:
    """``frames`` in a random order drawn from ``generator`` (for every frame once, the order
    ``torch.randperm(len(frames))`` gives, as training drew it before events)."""
    return [frames[j] for j in torch.randperm(len(frames), generator=generator).tolist()]
