"""``InferenceMemo``: one tensor derived from others, kept between renders of a trained avatar.

A render without autograd recomputes what only depends on the avatar's own tensors (its
skinning weights through the weight MLP, its SH coefficients gathered into one tensor): the same
value every call until training or a load changes a tensor. The memo keeps the value while
autograd is off and every input is the same object at the same in-place version
(``Tensor._version``, which ``copy_``, optimizer steps and ``clamp_`` bump); anything else
recomputes it. With autograd on it never keeps a value, so training sees fresh graphs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor


class InferenceMemo:
    """A one-entry memo of ``compute()`` over ``inputs`` (module docstring). The value is shared
    between callers: read it, never modify it in place."""

    def __init__(self) -> None:
        self._entry: tuple[list[Tensor], list[int], Tensor] | None = None

    # A copy (``copy.deepcopy`` of an avatar, pickling) starts empty: its inputs are new tensors
    # anyway, and some values (sparse CSR weights) cannot be deep-copied.
    def __deepcopy__(self, memo: dict) -> InferenceMemo:
        return InferenceMemo()

    def __getstate__(self) -> dict:
        return {"_entry": None}

    def get(self, inputs: Sequence[Tensor], compute: Callable[[], Tensor]) -> Tensor:
        if torch.is_grad_enabled():
            self._entry = None
            return compute()
        versions = [t._version for t in inputs]
        entry = self._entry  # one read: another thread may replace it meanwhile
        if (
            entry is not None
            and len(entry[0]) == len(inputs)
            and all(a is b for a, b in zip(entry[0], inputs, strict=True))
            and entry[1] == versions
        ):
            return entry[2]
        value = compute()
        self._entry = (list(inputs), versions, value)
        return value
