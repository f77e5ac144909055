"""Gaussians seen through the eye's opening attach to the eyeball, not to the lid beside them.

A Gaussian follows the facial actions of its nearest template vertex (``Avatar.pose``). The
iris and the white of the eye are painted a millimetre or two in front of the body model's
eyeball, which is coarse, and beside the lid margin, which is dense: the nearest vertex of most
of them is a lid vertex. A blink then carries the painted iris down with the lid, over the
cheek, and the closed eye shows it (``docs/alignment.md``, "Gaussians seen through the eye's
opening").

:func:`eye_openings` finds each eye's opening on the template: the loop of skin-boundary
vertices around the eyeball (the lid margin), seen from the front (world +Z, the way the body
model faces at rest). :func:`attach_to_eyeballs` gives each Gaussian in front of the eyeball
whose frontal projection falls inside that loop (shrunk by ``INSET`` about its centre, so the
lashes on the margin stay with the lid) its nearest eyeball-front vertex instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

INSET = 0.9  # the loop is shrunk to this share about its centre: the margin's lashes stay on the lid
MARGIN_REACH = 0.02  # metres: the skin-boundary vertices this close to an eyeball are its lid margin


@dataclass(frozen=True)
class EyeOpening:
    """One eye on the template: ``outline [M, 2]`` the lid margin's frontal (x, y) loop, in order;
    ``eyeball [K]`` the eyeball-front vertex ids; ``depth``: the eyeball centre's z (Gaussians
    behind it are left alone)."""

    outline: Tensor
    eyeball: Tensor
    depth: float


def eye_openings(template: Tensor, faces: Tensor, skin: Tensor, eyeballs: list[Tensor]) -> list[EyeOpening]:
    """The openings of ``eyeballs`` (each [K] vertex ids of one eye's front) on ``template [V, 3]``
    with ``faces [F, 3]``; ``skin [V]`` bool the skin vertices whose faces border the eyes."""
    tri = faces[skin[faces].all(dim=-1)]
    edges = torch.cat([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]).sort(dim=-1).values
    unique, count = torch.unique(edges, dim=0, return_counts=True)
    boundary = torch.unique(unique[count == 1])  # vertices on an edge of one skin face only
    out = []
    for ids in eyeballs:
        centre = template[ids].mean(dim=0)
        margin = boundary[(template[boundary] - centre).norm(dim=-1) < MARGIN_REACH]
        if len(margin) < 3:
            continue
        xy = template[margin, :2]
        mid = xy.mean(dim=0)
        angle = torch.atan2(xy[:, 1] - mid[1], xy[:, 0] - mid[0])
        outline = mid + INSET * (xy[angle.argsort()] - mid)
        out.append(EyeOpening(outline, ids, float(centre[2])))
    return out


def inside(points: Tensor, polygon: Tensor) -> Tensor:
    """[N] bool: ``points [N, 2]`` inside the closed ``polygon [M, 2]`` (even-odd rule)."""
    a, b = polygon, polygon.roll(-1, dims=0)  # [M, 2] the edges a -> b
    px, py = points[:, None, 0], points[:, None, 1]
    crosses = (a[:, 1] > py) != (b[:, 1] > py)
    t = (py - a[:, 1]) / (b[:, 1] - a[:, 1]).where(crosses, torch.ones_like(b[:, 1]))
    x_at = a[:, 0] + t * (b[:, 0] - a[:, 0])
    return ((crosses & (px < x_at)).sum(dim=1) % 2) == 1


def attach_to_eyeballs(
    means: Tensor, vertex_ids: Tensor, template: Tensor, openings: list[EyeOpening]
) -> Tensor:
    """``vertex_ids [N]`` with the Gaussians (canonical ``means [N, 3]``) seen through an opening
    attached to their nearest vertex of that eyeball's front on ``template [V, 3]``."""
    out = vertex_ids.clone()
    for eye in openings:
        front = means[:, 2] > eye.depth
        seen = front & inside(means[:, :2], eye.outline.to(means))
        if bool(seen.any()):
            nearest = torch.cdist(means[seen], template[eye.eyeball]).argmin(dim=-1)
            out[seen] = eye.eyeball.to(out.device)[nearest]
    return out
