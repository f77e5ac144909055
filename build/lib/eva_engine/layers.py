"""Layers initialised from an explicit ``torch.Generator`` instead of torch's process-global
random state, so a model's initial weights depend on its own seed only (two trainings in one
process, or in two threads, never share a random stream)."""

from __future__ import annotations

import math
from typing import TypeVar

import torch
from torch import nn

Layer = TypeVar("Layer", nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d)


def seeded_layer(cls: type[Layer], *args, generator: torch.Generator, **kwargs) -> Layer:
    """``cls(*args, **kwargs)`` initialised the way torch initialises it (``reset_parameters``:
    Kaiming-uniform weight with a = sqrt(5), bias uniform in +-1/sqrt(fan_in)), drawn from
    ``generator``: the same values as torch's own after ``torch.manual_seed`` with the same seed."""
    layer = nn.utils.skip_init(cls, *args, **kwargs)
    with torch.no_grad():
        nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
        if layer.bias is not None:
            fan_in = layer.weight[0].numel()
            bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
            nn.init.uniform_(layer.bias, -bound, bound, generator=generator)
    return layer
