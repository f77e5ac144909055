"""The skinning's compiled C++ kernel against its torch steps (``avatar/skinning.py``).

Both compute the same blend, Gram-Schmidt rotation, quaternion (roma's Shepperd variant) and
Hamilton product, so outputs and every gradient must agree: to ~1e-12 in float64 and within
float32 rounding in float32, on random and degenerate inputs alike.
"""

from __future__ import annotations

import math
import shutil

import pytest
import roma
import torch

from eva_engine.avatar import skinning
from eva_engine.avatar.skinning import SKINNING, skin_gaussians
from eva_engine.native import KernelUnavailableError

HAVE_COMPILER = shutil.which("c++") is not None and shutil.which("ninja") is not None


@pytest.fixture(scope="module")
def compiled():
    """The compiled kernel; a machine with a compiler must be able to build it."""
    if SKINNING.load() is None:
        if HAVE_COMPILER:
            pytest.fail(f"the skinning kernel did not build: {SKINNING.unavailable_reason()}")
        pytest.skip("no C++ compiler and ninja on this machine: the torch skinning runs")
    return SKINNING.load()


def random_inputs(n: int, j: int, dtype=torch.float64, seed: int = 0):
    """Canonical Gaussians, softmax weights and rigid bone transforms (leaves requiring grad)."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype)
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    weights = torch.softmax(3 * torch.randn(n, j, generator=gen, dtype=dtype), dim=-1)
    transforms = torch.eye(4, dtype=dtype).repeat(j, 1, 1)
    transforms[:, :3, :3] = roma.unitquat_to_rotmat(torch.randn(j, 4, generator=gen, dtype=dtype))
    transforms[:, :3, 3] = torch.randn(j, 3, generator=gen, dtype=dtype)
    return [t.requires_grad_(True) for t in (means, quats, weights, transforms)]


def skin_with_grads(inputs, kernel: str, seed: int = 1):
    """Outputs and the gradients of a random linear function of all three outputs."""
    outs = skin_gaussians(*inputs, kernel=kernel)
    gen = torch.Generator().manual_seed(seed)
    loss = sum((o * torch.randn(o.shape, generator=gen, dtype=o.dtype)).sum() for o in outs)
    return [o.detach() for o in outs], torch.autograd.grad(loss, inputs)


def assert_kernels_agree(inputs, atol: float, rtol: float):
    (out_c, grad_c), (out_t, grad_t) = skin_with_grads(inputs, "cpp"), skin_with_grads(inputs, "torch")
    for name, a, b in zip(("means", "quats", "rotations"), out_c, out_t, strict=True):
        torch.testing.assert_close(a, b, atol=atol, rtol=rtol, msg=lambda m, n=name: f"{n}: {m}")
    for name, a, b in zip(("means", "quats", "weights", "transforms"), grad_c, grad_t, strict=True):
        assert torch.isfinite(a).all(), name
        torch.testing.assert_close(a, b, atol=atol, rtol=rtol, msg=lambda m, n=name: f"d {n}: {m}")


@pytest.mark.parametrize("n, j", [(1, 1), (200, 7), (64, 104)])
def test_compiled_matches_torch_in_float64(compiled, n, j):
    assert_kernels_agree(random_inputs(n, j), atol=1e-11, rtol=1e-10)


def test_compiled_matches_torch_in_float32(compiled):
    # -march=native lets GCC fuse multiply-adds where the CPU has FMA, so the last float32 bits
    # differ by CPU: on an AMD EPYC one of 31,200 weight gradients (0.65) is 1.2e-4 off. The
    # float64 tests above hold the kernels to 1e-8.
    assert_kernels_agree(random_inputs(300, 104, torch.float32), atol=2e-4, rtol=1e-4)


def test_compiled_matches_torch_on_degenerate_blends(compiled):
    means, quats, weights, transforms = (t.detach() for t in random_inputs(8, 3))
    weights[0] = 0.0  # no weight at all: the blended matrix is zero
    weights[1] = torch.tensor([0.5, 0.5, 0.0])  # two opposite rotations cancel:
    transforms[1, :3, :3] = -transforms[0, :3, :3].clone()  # a zero 3x3 block
    weights[2] = torch.tensor([1.0, 0.0, 0.0])  # one bone exactly
    quats[3] = 0.0  # the zero quaternion stays zero
    means[4] = 1e6  # far away
    transforms[2, :3, :3] *= 1e-9  # a bone shrunk to (almost) nothing
    weights[5] = torch.tensor([0.0, 0.0, 1.0])
    for angle in (math.pi, math.pi / 2):  # 180 and 90 degrees: Shepperd's other branches
        inputs = [t.clone().requires_grad_(True) for t in (means, quats, weights, transforms)]
        with torch.no_grad():
            inputs[3][0, :3, :3] = roma.rotvec_to_rotmat(torch.tensor([angle, 0.0, 0.0], dtype=torch.float64))
        assert_kernels_agree(inputs, atol=1e-8, rtol=1e-8)


def test_every_shepperd_branch_is_exercised(compiled):
    # Rotations of 170 degrees about each axis pick the x, y and z rows; small ones the w row.
    rotvecs = torch.tensor([[3.0, 0, 0], [0, 3.0, 0], [0, 0, 3.0], [0.1, 0.2, 0.3]], dtype=torch.float64)
    means, quats, weights, _ = random_inputs(4, 4)
    transforms = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    transforms[:, :3, :3] = roma.rotvec_to_rotmat(rotvecs)
    weights = torch.eye(4, dtype=torch.float64).requires_grad_(True)
    assert_kernels_agree([means, quats, weights, transforms.requires_grad_(True)], atol=1e-11, rtol=1e-10)


def test_compiled_gradients_pass_gradcheck(compiled):
    inputs = random_inputs(6, 3, seed=3)
    assert torch.autograd.gradcheck(lambda *x: skin_gaussians(*x, kernel="cpp"), inputs, eps=1e-6, atol=1e-6)


def test_compiled_is_deterministic_for_a_thread_count(compiled):
    inputs = random_inputs(5000, 104, torch.float32, seed=4)
    first = skin_with_grads(inputs, "cpp")
    second = skin_with_grads(inputs, "cpp")
    for a, b in zip([*first[0], *first[1]], [*second[0], *second[1]], strict=True):
        assert torch.equal(a, b)


def test_kernel_choice(compiled, monkeypatch):
    like = torch.zeros(1)
    monkeypatch.delenv(SKINNING.env, raising=False)
    assert SKINNING.resolve("auto", like) == "cpp"
    monkeypatch.setenv(SKINNING.env, "torch")
    assert SKINNING.resolve("auto", like) == "torch"
    assert SKINNING.resolve("cpp", like) == "cpp"  # an explicit argument wins
    monkeypatch.delenv(SKINNING.env)
    assert SKINNING.resolve("auto", like.half()) == "torch"  # a dtype the kernel does not take
    with pytest.raises(KernelUnavailableError):
        SKINNING.resolve("cpp", like.half())
    assert skinning.ORTHONORMALIZE_EPS > 0
