"""The two small MLPs of EVA §3.1 and their positional encoding.

- ``LBSWeightOffsets``: gamma(p_c) -> per-joint offsets w' [N, J]; the skinning weights are
  w = softmax(log(w_body + eps) + w') (``blend_skinning_weights``).
- ``PoseRefiner``: theta = theta_in (x) f(theta_in). We follow EVA's official code (GauHuman's
  ``BodyPoseRefiner``, one network per part): for each part (body, hands, face) an MLP maps the
  part's input joint rotations (axis-angle, flattened) to a small per-joint rotation delta, and
  the refined rotation of joint j is R(theta_j) R(delta_j) (rotation composition, the "(x)").
  The root orientation and translation are not refined.

Both last layers start uniform in +-``out_init`` (1e-5) with zero bias, so at initialisation the
skinning is the body model's and the pose is the input pose (to ~1e-5).
"""

from __future__ import annotations

import math

import roma
import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from eva_engine.body.model import PART_NAMES
from eva_engine.layers import seeded_layer


def positional_encoding(x: Tensor, frequencies: int) -> Tensor:
    """NeRF's gamma: [..., D] -> [..., D (1 + 2 L)] = (x, sin(2^k pi x), cos(2^k pi x)), k < L."""
    if frequencies == 0:
        return x
    scales = (2.0 ** torch.arange(frequencies, device=x.device, dtype=x.dtype)) * math.pi
    xb = x[..., None, :] * scales[:, None]  # [..., L, D]
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1).flatten(-2)
    return torch.cat([x, enc], dim=-1)


def make_mlp(
    d_in: int, d_out: int, width: int, depth: int, out_init: float, generator: torch.Generator
) -> nn.Sequential:
    """``depth`` hidden ReLU layers of ``width`` (torch's default initialisation); last layer
    uniform(+-out_init), bias 0; every draw from ``generator``."""
    layers: list[nn.Module] = []
    d = d_in
    for _ in range(depth):
        layers += [seeded_layer(nn.Linear, d, width, generator=generator), nn.ReLU()]
        d = width
    last = seeded_layer(nn.Linear, d, d_out, generator=generator)
    with torch.no_grad():
        nn.init.uniform_(last.weight, -out_init, out_init, generator=generator)
        nn.init.zeros_(last.bias)
    layers.append(last)
    return nn.Sequential(*layers)


def relu_mlp(
    x: Tensor,
    mlp: nn.Sequential,
    chunk: int = 4096,
    log_prior: tuple[Tensor, Tensor] | None = None,
    bf16: bool = False,
) -> Tensor:
    """``mlp(x)`` for a ``make_mlp`` network, or with ``log_prior = (table [V, D_out], rows [N])``
    the softmax ``softmax(mlp(x) + table[rows])``: the same values and gradients (parameters and
    ``x``) as autograd through the layers, to rounding, computed ``chunk`` rows at a time so that
    each chunk's activations stay in cache (at ~30k Gaussians, passes over [N, width] tensors cost
    as much as the matrix products on CPU). x: [N, D_in] -> [N, D_out].

    ``bf16``: with autograd, the layers' products in bfloat16 (inputs, weights, activations and
    the gradients flowing back); the output, the softmax and the parameters' gradients stay
    float32. Where the CPU multiplies bfloat16 natively (AVX512-BF16, AMX) that is ~1.5x faster
    (``bench/mlp_precision.py``); elsewhere it is emulated, and slower."""
    linears = [m for m in mlp if isinstance(m, nn.Linear)]
    if len(linears) * 2 - 1 != len(mlp):
        raise ValueError("relu_mlp takes make_mlp's Linear, (ReLU, Linear)* networks")
    if not torch.is_grad_enabled():
        out = mlp(x)
        return out if log_prior is None else torch.softmax(out + log_prior[0][log_prior[1]], dim=-1)
    params = [t for layer in linears for t in (layer.weight, layer.bias)]
    table, rows = log_prior if log_prior is not None else (None, None)
    dtype = torch.bfloat16 if bf16 else x.dtype
    return _ChunkedReluMLP.apply(x, chunk, table, rows, dtype, *params)


class _ChunkedReluMLP(torch.autograd.Function):
    """Linear, (ReLU, Linear)* [+ log prior, softmax], ``chunk`` rows at a time; each chunk's
    layer inputs (and softmax output) are kept for the backward, which walks the chunk back. The
    products run in ``dtype`` (the parameters' own, or bfloat16: ``relu_mlp``)."""

    @staticmethod
    def forward(ctx, x, chunk, table, rows, dtype, *params):
        n_layers = len(params) // 2
        cast = [p.to(dtype) for p in params]  # the parameters themselves when dtype is theirs
        kept, outs = [], []  # kept: per chunk, the input of every layer
        for s in range(0, x.shape[0], chunk):
            h = x[s : s + chunk].to(dtype)
            for i in range(n_layers):
                kept.append(h)
                h = torch.addmm(cast[2 * i + 1], h, cast[2 * i].t())
                if i < n_layers - 1:
                    h.relu_()
            h = h.to(x.dtype)
            if table is not None:
                h = torch.softmax(h.add_(table.index_select(0, rows[s : s + chunk])), dim=-1)
            outs.append(h)
        out = torch.cat(outs) if len(outs) != 1 else outs[0]
        ctx.save_for_backward(*kept, *cast, *([out] if table is not None else []))
        ctx.layers, ctx.chunk, ctx.softmax = n_layers, chunk, table is not None
        ctx.dtypes = (x.dtype, params[0].dtype)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        n_layers, chunk = ctx.layers, ctx.chunk
        x_dtype, param_dtype = ctx.dtypes
        saved = ctx.saved_tensors
        if ctx.softmax:
            *saved, out = saved
        kept, params = saved[: -2 * n_layers], saved[-2 * n_layers :]
        grads = [torch.zeros_like(p, dtype=param_dtype) for p in params]
        need_x = ctx.needs_input_grad[0]
        grad_x = []
        grad = grad.contiguous()
        for c, s in enumerate(range(0, grad.shape[0], chunk)):
            g = grad[s : s + chunk]
            if ctx.softmax:  # d softmax: w (g - <w, g>)
                w = out[s : s + chunk]
                g = torch._softmax_backward_data(g, w, -1, w.dtype)
            g = g.to(params[0].dtype)
            for i in reversed(range(n_layers)):
                a = kept[c * n_layers + i]  # layer i's input: for i > 0 a ReLU's output
                if g.dtype == param_dtype:
                    grads[2 * i].addmm_(g.t(), a)
                    grads[2 * i + 1] += g.sum(dim=0)
                else:  # the products in g's precision, their sum in the parameters'
                    grads[2 * i] += (g.t() @ a).to(param_dtype)
                    grads[2 * i + 1] += g.sum(dim=0, dtype=param_dtype)
                if i > 0:
                    g = torch.ops.aten.threshold_backward(g @ params[2 * i], a, 0.0)
                elif need_x:
                    grad_x.append((g @ params[0]).to(x_dtype))
        gx = (torch.cat(grad_x) if len(grad_x) != 1 else grad_x[0]) if need_x else None
        return gx, None, None, None, None, *grads


class LBSWeightOffsets(nn.Module):
    """f_w: canonical centres [N, 3] -> LBS weight offsets [N, J] (EVA eq. for w_k).
    generator: the initial weights' random draws (None: a generator seeded 0)."""

    def __init__(
        self,
        num_joints: int,
        frequencies: int,
        width: int,
        depth: int,
        out_init: float,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.frequencies = frequencies
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.mlp = make_mlp(3 * (1 + 2 * frequencies), num_joints, width, depth, out_init, generator)

    def forward(self, means: Tensor) -> Tensor:
        return relu_mlp(positional_encoding(means, self.frequencies), self.mlp)

    def skinning_weights(self, means: Tensor, log_base: Tensor, rows: Tensor, bf16: bool = False) -> Tensor:
        """``blend_log_skinning_weights(log_base[rows], self(means))`` [N, J] in one chunked pass
        (log_base: [V, J] log(w_body + eps) per body vertex; rows: [N] each Gaussian's vertex;
        ``bf16``: the products in bfloat16 while training, ``relu_mlp``)."""
        x = positional_encoding(means, self.frequencies)
        return relu_mlp(x, self.mlp, log_prior=(log_base, rows), bf16=bf16)


def blend_skinning_weights(base: Tensor, offsets: Tensor | None, eps: float = 1e-8) -> Tensor:
    """w = softmax(log(base + eps) + offsets). base: [N, J] rows summing to 1; offsets: [N, J] or
    None (then w = base renormalised with eps, i.e. the body model's weights)."""
    return blend_log_skinning_weights(torch.log(base + eps), offsets)


def blend_log_skinning_weights(log_base: Tensor, offsets: Tensor | None) -> Tensor:
    """``blend_skinning_weights`` from log_base = log(base + eps) [N, J] (which an avatar computes
    once per body vertex rather than per Gaussian and step)."""
    return torch.softmax(log_base if offsets is None else log_base + offsets, dim=-1)


class PoseRefiner(nn.Module):
    """Per-part pose correction (see the module docstring).

    joint_part_ids: [P] part index of each pose joint (``model.pose_joint_names`` order).
    forward: joints [B, P, 3] axis-angle -> refined joints [B, P, 3].
    generator: the initial weights' random draws (None: a generator seeded 0).
    """

    joint_part_ids: Tensor

    def __init__(
        self,
        joint_part_ids: Tensor,
        width: int,
        depth: int,
        out_init: float,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.register_buffer("joint_part_ids", joint_part_ids.to(torch.int64).clone())
        self.mlps = nn.ModuleDict()
        generator = generator if generator is not None else torch.Generator().manual_seed(0)
        for i, part in enumerate(PART_NAMES):
            n = int((self.joint_part_ids == i).sum())
            if n:
                self.mlps[part] = make_mlp(3 * n, 3 * n, width, depth, out_init, generator)

    def deltas(self, joints: Tensor) -> Tensor:
        """[B, P, 3] predicted rotation deltas (axis-angle)."""
        out = torch.zeros_like(joints)
        for i, part in enumerate(PART_NAMES):
            if part not in self.mlps:
                continue
            idx = torch.nonzero(self.joint_part_ids == i).squeeze(1)
            x = joints[:, idx]
            out[:, idx] = self.mlps[part](x.flatten(1)).view_as(x)
        return out

    def forward(self, joints: Tensor) -> Tensor:
        return roma.rotvec_composition([joints, self.deltas(joints)])
