"""Motion over time: temporal smoothing and resampling of body parameters.

Joint rotations (``root_orient``, ``joints``, axis-angle) are smoothed and interpolated as unit
quaternions (w, x, y, z), made sign-continuous along time first (q and -q are one rotation, and
an average across a sign flip would cancel); translations and expressions linearly. Times are in
seconds, so a clip with dropped frames (no person found) is smoothed and resampled by when its
frames happened, not by their index.
"""

from __future__ import annotations

import torch
from torch import Tensor

from eva_engine.body.params import BodyParams

_EPS = 1e-8


def axis_angle_to_quat(rotvec: Tensor) -> Tensor:
    """[..., 3] axis-angle (radians) -> [..., 4] unit quaternions (w, x, y, z); exact near zero."""
    angle = rotvec.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 - a^2/48 as a -> 0 (no 0/0).
    small = angle < 1e-4
    k = torch.where(small, 0.5 - angle * angle / 48.0, torch.sin(half) / angle.clamp_min(1e-12))
    return torch.cat([torch.cos(half), rotvec * k], dim=-1)


def quat_to_axis_angle(quat: Tensor) -> Tensor:
    """[..., 4] quaternions (w, x, y, z; any norm, not zero) -> [..., 3] axis-angle with angle in
    [0, pi] (the shorter way round)."""
    q = quat / quat.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    q = torch.where(q[..., :1] < 0, -q, q)  # w >= 0: angle <= pi
    w, xyz = q[..., :1], q[..., 1:]
    s = xyz.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, w)
    small = s < 1e-6
    # angle / sin(angle/2) -> 2 (1 + s^2 / 6) for small angles.
    k = torch.where(small, 2.0 + s * s / 3.0, angle / s.clamp_min(1e-12))
    return xyz * k


def continuous_quats(quats: Tensor) -> Tensor:
    """[T, ..., 4] -> the same rotations with each q_t's sign chosen so that q_t . q_{t-1} >= 0."""
    out = quats.clone()
    for t in range(1, out.shape[0]):
        flip = (out[t] * out[t - 1]).sum(-1, keepdim=True) < 0
        out[t] = torch.where(flip, -out[t], out[t])
    return out


def _check_times(params: BodyParams, times: Tensor) -> Tensor:
    times = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    if times.shape[0] != params.batch_size:
        raise ValueError(f"{times.shape[0]} times for {params.batch_size} frames")
    if not torch.isfinite(times).all() or (times.diff() <= 0).any():
        raise ValueError("frame times must be finite and strictly increasing")
    return times


def _blend(params: BodyParams, weights: Tensor) -> BodyParams:
    """Rows of ``weights [N, T]`` (each sums to 1) mix the T frames into N: quaternion averages
    (normalised) for rotations, weighted sums for the rest."""
    w = weights.to(params.joints.dtype)

    def rotations(rotvec: Tensor) -> Tensor:  # [T, ..., 3] -> [N, ..., 3]
        q = continuous_quats(axis_angle_to_quat(rotvec))
        mixed = torch.einsum("nt,t...->n...", w, q)
        return quat_to_axis_angle(mixed)

    def linear(x: Tensor) -> Tensor:
        return torch.einsum("nt,t...->n...", w, x)

    return BodyParams(
        root_orient=rotations(params.root_orient),
        transl=linear(params.transl),
        joints=rotations(params.joints),
        expression=linear(params.expression),
        shape=linear(params.shape),
    )


def smooth_params(params: BodyParams, times: Tensor, sigma_s: float) -> BodyParams:
    """Gaussian smoothing over time: params [T] at ``times [T]`` (seconds, increasing) -> [T].

    ``sigma_s``: the kernel's standard deviation in seconds (0: unchanged). Each frame averages
    its neighbours within 3 sigma, weighted by exp(-dt^2 / (2 sigma^2)) and renormalised at the
    clip's ends, so a held pose stays exactly itself.
    """
    if sigma_s < 0:
        raise ValueError(f"sigma_s must be >= 0, got {sigma_s}")
    times = _check_times(params, times)
    if sigma_s == 0 or params.batch_size == 1:
        return params
    dt = times[:, None] - times[None, :]
    weights = torch.exp(-0.5 * (dt / sigma_s) ** 2) * (dt.abs() <= 3.0 * sigma_s)
    weights = weights / weights.sum(1, keepdim=True)
    return _blend(params, weights)


def resample_params(params: BodyParams, times: Tensor, new_times: Tensor) -> BodyParams:
    """params [T] at ``times [T]`` -> [N] at ``new_times [N]``: linear interpolation between the
    two neighbouring frames (normalised quaternion lerp for rotations); times outside the clip
    take its first or last frame."""
    times = _check_times(params, times)
    new_times = torch.as_tensor(new_times, dtype=torch.float64).reshape(-1)
    t = new_times.clamp(times[0], times[-1])
    hi = torch.searchsorted(times, t).clamp(1, max(params.batch_size - 1, 1))
    lo = hi - 1
    weights = torch.zeros(len(t), params.batch_size, dtype=torch.float64)
    if params.batch_size == 1:
        weights[:, 0] = 1.0
        return _blend(params, weights)
    span = times[hi] - times[lo]
    a = ((t - times[lo]) / span).clamp(0.0, 1.0)
    rows = torch.arange(len(t))
    weights[rows, lo] = 1.0 - a
    weights[rows, hi] += a
    return _blend(params, weights)


def frame_times(start: float, end: float, fps: float) -> Tensor:
    """[N] float64 times ``start, start + 1/fps, ...`` up to ``end`` (inclusive, with a little
    slack for rounding): the output frames of a clip running from ``start`` to ``end``."""
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    if end < start:
        raise ValueError(f"end {end} is before start {start}")
    count = int((end - start) * fps + 1e-6) + 1
    return start + torch.arange(count, dtype=torch.float64) / fps
