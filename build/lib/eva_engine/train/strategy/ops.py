"""Density-control operations that keep every per-Gaussian tensor aligned (gsplat's ``ops``).

Each op edits, row for row and together: the learnable ``splats`` (new ``nn.Parameter``s), their
Adam state (``exp_avg``, ``exp_avg_sq``: kept for surviving rows, zero for new rows), the
Gaussians' per-Gaussian buffers (part ids, template vertex ids; children inherit the parent's),
and every per-Gaussian tensor of the strategy ``state`` (new rows zero).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from eva_engine.avatar.gaussians import CanonicalGaussians
from eva_engine.render import quat_to_rotmat

Optimizers = dict[str, torch.optim.Optimizer]


def _update(
    gaussians: CanonicalGaussians,
    optimizers: Optimizers,
    state: dict,
    param_fn: Callable[[str, Tensor], Tensor],
    optim_fn: Callable[[str, Tensor], Tensor],
    buffer_fn: Callable[[Tensor], Tensor],
    state_fn: Callable[[Tensor], Tensor],
) -> None:
    n = len(gaussians)
    for name in list(gaussians.splats.keys()):
        old = gaussians.splats[name]
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        opt = optimizers.get(name)
        if opt is not None:
            group = opt.param_groups[0]
            if len(group["params"]) != 1 or group["params"][0] is not old:
                raise RuntimeError(f"optimizer {name!r} does not hold exactly splats[{name!r}]")
            st = opt.state.pop(old, {})
            for key, value in st.items():
                if key != "step" and torch.is_tensor(value) and value.shape[:1] == (n,):
                    st[key] = optim_fn(key, value)
            group["params"][0] = new
            if st:
                opt.state[new] = st
        gaussians.splats[name] = new
    for name, buf in gaussians.buffers_per_gaussian().items():
        gaussians.set_buffer(name, buffer_fn(buf))
    for key, value in state.items():
        if torch.is_tensor(value) and value.ndim >= 1 and value.shape[0] == n:
            state[key] = state_fn(value)


def duplicate(gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict, mask: Tensor) -> None:
    """Clone the Gaussians in ``mask [N]`` (bool): copies appended at the end, same parameters."""
    sel = torch.nonzero(mask).squeeze(1)

    def rows(x: Tensor) -> Tensor:
        return torch.cat([x, x[sel]])

    def zeros(x: Tensor) -> Tensor:
        return torch.cat([x, x.new_zeros((len(sel), *x.shape[1:]))])

    _update(gaussians, optimizers, state, lambda _, p: rows(p), lambda _, v: zeros(v), rows, zeros)


def split(
    gaussians: CanonicalGaussians,
    optimizers: Optimizers,
    state: dict,
    mask: Tensor,
    n_split: int = 2,
    scale_divisor: float = 1.6,
    generator: torch.Generator | None = None,
    keep_parents: bool = False,
) -> None:
    """Replace each Gaussian in ``mask [N]`` by ``n_split`` children sampled from it (3DGS):
    centres drawn from the parent's Gaussian, scales divided by 0.8 n_split (1.6 for 2).
    ``keep_parents``: the parents stay too (GauHuman's clone is ``n_split=1, scale_divisor=1``
    with the parent kept: a copy displaced by a sample of the parent, not an exact copy)."""
    sel = torch.nonzero(mask).squeeze(1)
    keep = torch.arange(len(mask), device=mask.device) if keep_parents else torch.nonzero(~mask).squeeze(1)
    splats = gaussians.splats
    scales = torch.exp(splats["scales"].detach()[sel])  # [M, 3]
    rot = quat_to_rotmat(splats["quats"].detach()[sel])  # [M, 3, 3]
    noise = torch.randn(n_split, len(sel), 3, generator=generator).to(scales)
    offsets = torch.einsum("mij,smj->smi", rot, noise * scales)  # [S, M, 3]

    def param_fn(name: str, p: Tensor) -> Tensor:
        if name == "means":
            children = (p[sel][None] + offsets).reshape(-1, 3)
        elif name == "scales":
            children = torch.log(scales / scale_divisor).repeat(n_split, 1)
        else:
            children = p[sel].repeat(n_split, *[1] * (p.ndim - 1))
        return torch.cat([p[keep], children])

    def rows(x: Tensor) -> Tensor:
        return torch.cat([x[keep], x[sel].repeat(n_split, *[1] * (x.ndim - 1))])

    def zeros(x: Tensor) -> Tensor:
        return torch.cat([x[keep], x.new_zeros((n_split * len(sel), *x.shape[1:]))])

    _update(gaussians, optimizers, state, param_fn, lambda _, v: zeros(v), rows, zeros)


def merge(gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict, pairs: Tensor) -> None:
    """Replace each pair ``pairs [M, 2]`` (row indices, every Gaussian in at most one pair) by one
    Gaussian (GauHuman's KL merge): the centre, colours and opacity logit are the pair's means;
    the scales are the first one's divided by 0.8 and its rotation is kept. Per-Gaussian buffers
    come from the first of the pair; new rows of optimizer and strategy state are zero."""
    n = len(gaussians)
    first, second = pairs[:, 0], pairs[:, 1]
    merged = torch.zeros(n, dtype=torch.bool, device=pairs.device)
    merged[first] = True
    merged[second] = True
    if int(merged.sum()) != 2 * len(pairs):
        raise ValueError("merge pairs must not share a Gaussian")
    keep = torch.nonzero(~merged).squeeze(1)

    def param_fn(name: str, p: Tensor) -> Tensor:
        if name == "scales":
            children = p[first] - math.log(0.8)
        elif name == "quats":
            children = p[first]
        else:
            children = 0.5 * (p[first] + p[second])
        return torch.cat([p[keep], children])

    def rows(x: Tensor) -> Tensor:
        return torch.cat([x[keep], x[first]])

    def zeros(x: Tensor) -> Tensor:
        return torch.cat([x[keep], x.new_zeros((len(pairs), *x.shape[1:]))])

    _update(gaussians, optimizers, state, param_fn, lambda _, v: zeros(v), rows, zeros)


def remove(gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict, mask: Tensor) -> None:
    """Delete the Gaussians in ``mask [N]``."""
    keep = torch.nonzero(~mask).squeeze(1)

    def rows(x: Tensor) -> Tensor:
        return x[keep]

    _update(gaussians, optimizers, state, lambda _, p: rows(p), lambda _, v: rows(v), rows, rows)


def reset_opacity(gaussians: CanonicalGaussians, optimizers: Optimizers, state: dict, value: float) -> None:
    """Clamp every opacity to at most ``value`` (3DGS's periodic reset); its Adam state is zeroed."""
    logit = torch.logit(torch.tensor(value)).item()

    def param_fn(name: str, p: Tensor) -> Tensor:
        return p.clamp_max(logit) if name == "opacities" else p

    def optim_fn(_: str, v: Tensor) -> Tensor:
        return v

    # Only the opacity optimizer's moments are reset (the others keep theirs).
    _update(gaussians, optimizers, state, param_fn, optim_fn, lambda x: x, lambda x: x)
    opt = optimizers.get("opacities")
    if opt is not None:
        for v in opt.state[gaussians.splats["opacities"]].values():
            if torch.is_tensor(v) and v.ndim >= 1:
                v.zero_()
