"""``InferenceMemo``: one value derived from tensors, kept between renders of a trained avatar.

A render without autograd recomputes what only depends on the avatar's own tensors (its
skinning weights through the weight MLP, its SH coefficients gathered into one tensor, the body
model's rest mesh for the avatar's shape): the same value every call until training or a load
changes a tensor. The memo keeps the value while
autograd is off and every input is the same object at the same in-place version
(``Tensor._version``, which ``copy_``, optimizer steps and ``clamp_`` bump), and, for a value
that also depends on a request (a pose), while the ``key`` tensors hold the same values as last
time (compared by value: each request brings new tensors); anything else recomputes it. With
autograd on it never keeps a value, so training sees fresh graphs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor


class InferenceMemo:
    """A one-entry memo of ``compute()`` over ``inputs`` (module docstring). The value is shared
    between callers: read it, never modify it in place."""

    def __init__(self) -> None:
        self._entry: tuple[list[Tensor], list[int], list[Tensor], Any] | None = None

    # A copy (``copy.deepcopy`` of an avatar, pickling) starts empty: its inputs are new tensors
    # anyway, and some values (sparse CSR weights) cannot be deep-copied.
    def __deepcopy__(self, memo: dict) -> InferenceMemo:
        return InferenceMemo()

    def __getstate__(self) -> dict:
        return {"_entry": None}

    def get(self, inputs: Sequence[Tensor], compute: Callable[[], Any], key: Sequence[Tensor] = ()) -> Any:
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
            and len(entry[2]) == len(key)
            and all(_same(a, b) for a, b in zip(entry[2], key, strict=True))
        ):
            return entry[3]
        value = compute()
        self._entry = (list(inputs), versions, [k.detach().clone() for k in key], value)
        return value


def _same(a: Tensor, b: Tensor) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.device == b.device and torch.equal(a, b)
