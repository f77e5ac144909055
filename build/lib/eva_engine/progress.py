"""``ProgressEvent``: the one shape of every progress report, from the engine's long calls
(preprocessing, fitting, training, animation, synthetic data) to the job records of the service
and the command line's progress bars. A producer takes a ``Progress`` callback and calls it with
events; a consumer maps them (``rescaled``) or shows them."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class ProgressEvent:
    """stage: what runs now (e.g. ``"detect"``, ``"train"``); done of total units (frames,
    iterations; ``total`` 0: unknown); message: the same for people; what the stage knows about
    itself: loss, num_gaussians, elapsed and eta (remaining) seconds."""

    stage: str
    done: float = 0
    total: float = 0
    message: str | None = None
    loss: float | None = None
    num_gaussians: int | None = None
    elapsed: float | None = None
    eta: float | None = None

    @property
    def fraction(self) -> float:
        """done / total in [0, 1] (0 while the total is unknown)."""
        return min(max(self.done / self.total, 0.0), 1.0) if self.total > 0 else 0.0

    def rescaled(self, stage: str, start: float, end: float) -> ProgressEvent:
        """This event as the part ``start..end`` (fractions) of ``stage``: its ``fraction`` maps
        linearly onto it, and done / total become that fraction of 1."""
        return dataclasses.replace(self, stage=stage, done=start + (end - start) * self.fraction, total=1.0)


Progress = Callable[[ProgressEvent], None]
"""A progress callback."""
