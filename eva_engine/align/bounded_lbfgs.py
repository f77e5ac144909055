"""L-BFGS-B over torch tensors: L-BFGS whose variables may have box bounds (scipy's L-BFGS-B,
whose line search keeps the strong Wolfe conditions), for fit stages whose parameters have a
valid range (``FitConfig.bounded_expression``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits
from torch import Tensor

Bounds = tuple[float, float] | None


def minimize_bounded(
    tensors: Sequence[Tensor],
    bounds: Sequence[Bounds],
    loss_fn: Callable[[], Tensor],
    iterations: int,
    history_size: int,
) -> int:
    """Minimise ``loss_fn()`` over ``tensors`` in place, each inside its ``bounds`` ((lo, hi) for
    every entry, or None: free), for ``iterations`` L-BFGS-B iterations (or until the line search
    finds no decrease) with ``history_size`` correction pairs. Entries start clipped into their
    bounds. ``loss_fn`` reads the tensors and returns a scalar with a graph to them. Returns how
    many times it was called.

    The optimiser works in float64 (scipy's); the tensors keep their dtype.
    """
    if len(tensors) != len(bounds):
        raise ValueError(f"{len(tensors)} tensors but {len(bounds)} bounds")
    sizes = [t.numel() for t in tensors]
    pairs = [(-np.inf, np.inf) if b is None else b for b in bounds]
    lower = np.concatenate([np.full(n, float(lo)) for n, (lo, _) in zip(sizes, pairs, strict=True)])
    upper = np.concatenate([np.full(n, float(hi)) for n, (_, hi) in zip(sizes, pairs, strict=True)])
    x0 = torch.cat([t.detach().reshape(-1).double() for t in tensors]).numpy()
    calls = 0

    def assign(x: np.ndarray) -> None:
        with torch.no_grad():
            for t, part in zip(tensors, torch.from_numpy(x).split(sizes), strict=True):
                t.copy_(part.reshape(t.shape))

    def value_and_grad(x: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal calls
        calls += 1
        assign(x)
        for t in tensors:
            t.grad = None
        loss = loss_fn()
        loss.backward()
        grad = torch.cat([t.grad.reshape(-1).double() for t in tensors])
        return float(loss.detach()), grad.numpy()

    for t in tensors:
        t.requires_grad_(True)
    # One BLAS thread: L-BFGS-B's vector operations are small, OpenBLAS's idle threads spun
    # between its calls and took the cores from torch (the fit ran twice as long), and a
    # reduction order that depends on the thread count would make the fit depend on the machine.
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            result = minimize(
                value_and_grad,
                np.clip(x0, lower, upper),
                jac=True,
                method="L-BFGS-B",
                bounds=list(zip(lower, upper, strict=True)),
                # As torch's LBFGS with tolerance_change 0: run the iterations; 1.25 calls each at most.
                options={
                    "maxiter": iterations,
                    "maxfun": max(1, round(1.25 * iterations)),
                    "maxcor": history_size,
                    "ftol": 0.0,
                    "gtol": 0.0,
                },
            )
        assign(result.x)
    finally:
        for t in tensors:
            t.requires_grad_(False)
            t.grad = None
    return calls
