"""Colours that change with the facial expression.

An expression moves the Gaussians on the skin it deforms (``avatar/surface_frames.py``) but
keeps their colours. A closing eye needs more than motion: on a real video the avatar paints the
iris and the lash line on the Gaussians of the lid (it learns from the open eye, which is nearly
every frame), and a blink then slides that painted eye down the face instead of covering it with
skin (``docs/alignment.md``, "Where the gesturing clip's blink is lost"). An opening mouth shows
teeth and a dark interior that no rest-pose colour holds either.

So each Gaussian may carry a colour offset per *revealing* action, blended by the frame's
coefficients, as 3D Gaussian Blendshapes (Ma et al. 2024) blend the attributes of a head avatar:
``sh0(e) = sh0 + sum_k m_k clamp(e_k / r_k, -1, 1) delta_k``.

- The actions are those that cover or uncover something (``REVEALING_ACTIONS``: the lids over
  the eyes, the jaw over the mouth's interior); the others move skin whose colour moves with it.
  With all 52, the mouth's correlated actions learnt offsets that cancel on the training frames
  and not elsewhere: coloured speckles on held-out mouths. The default keeps the blinks only
  (``AvatarConfig.expression_colour_actions``): the jaw's offsets fit a take's few open-jaw
  frames and made the face worse in new poses.
- ``r_k`` is the largest coefficient of the action in the training frames
  (``expression_range``), so ``delta_k`` is the colour change at the most extreme training
  frame, and a coefficient beyond it does not extrapolate: a video whose fitted blinks reach
  0.47 gave saturated orange lids at blink 1 when the offsets scaled linearly. The geometry
  still follows the coefficient all the way.
- ``m_k`` is 1 for a Gaussian whose vertex the action moves by more than ``REACH`` of the
  action's largest displacement, and 0 elsewhere: a blink recolours the lids, not a hand that
  happens to move while the person blinks, and the jaw recolours the lips and chin, not the
  nose that Anny's jawOpen also moves a little (a pink nose tip on open-mouthed frames
  with an absolute 0.5 mm threshold).

At zero expression the colours are the rest colours exactly.

Shapes: N Gaussians, E expression coefficients, K revealing actions, V template vertices.
"""

from __future__ import annotations

import torch
from torch import Tensor

from eva_engine.body.model import BodyModel
from eva_engine.render.sh import SH_C0

REACH = 0.1  # the share of an action's largest displacement a vertex must move to be recoloured
LOCAL_RADIUS = 0.035  # metres around an action's most moved vertex: a lid and its brow, not the mouth
MIN_RANGE = 0.05  # an action (nearly) absent from training: its offsets learn nothing anyway
MAX_OFFSET = 1.0 / SH_C0  # an offset of at most the whole colour range per unit coefficient


def revealing_actions(names: list[str], wanted: tuple[str, ...] | None) -> list[int]:
    """Indices into ``names`` (a body model's expression names) of the ``wanted`` actions it has;
    all of them when ``wanted`` is None. A model with none of those names (SMPL-X's unnamed PCA
    coefficients, each of which moves the whole face) gets none: with every action the offsets
    learnt speckles that cancel on the training frames only."""
    if wanted is None:
        return list(range(len(names)))
    return [names.index(a) for a in wanted if a in names]


@torch.no_grad()
def action_reach(
    body: BodyModel, shape: Tensor, actions: list[int], reach: float = REACH, spread: float = 0.0
) -> Tensor:
    """[V, K] bool: the template vertices each of the K ``actions`` (expression indices) moves, at
    coefficient 1, by more than ``reach`` times the action's largest displacement (``body``'s
    rest pose with ``shape [S]``). With ``spread`` > 0 the reach is local and covers what the
    action covers: only the moved vertices within ``LOCAL_RADIUS`` of the most moved one (Anny's
    blinks also move the mouth's cavity by up to two thirds of the lid's travel, and the
    other eye's socket), and every vertex within ``spread`` metres of those on the neutral face
    (the eyeball behind a closing lid)."""
    k = len(actions)
    params = body.default_params(k + 1)
    params.shape = shape.to(params.shape).reshape(1, -1).expand(k + 1, -1).clone()
    params.expression[torch.arange(1, k + 1), torch.tensor(actions, dtype=torch.long)] = 1.0
    rest = body.canonical(params)  # [K + 1, V, 3]; row 0 is the neutral face
    moved = (rest[1:] - rest[:1]).norm(dim=-1)  # [K, V]
    hit = moved > reach * moved.amax(dim=1, keepdim=True)  # [K, V]
    if spread > 0:
        for a in range(k):
            centre = rest[0][moved[a].argmax()]
            seeds = hit[a] & ((rest[0] - centre).norm(dim=-1) < LOCAL_RADIUS)
            if bool(seeds.any()):
                hit[a] = seeds | (torch.cdist(rest[0], rest[0][seeds]).amin(dim=1) < spread)
    return hit.T.contiguous()


def expression_range(expression: Tensor, actions: list[int] | Tensor) -> Tensor:
    """[K] ``r_k``: each action's largest absolute coefficient over frames ``expression [F, E]``,
    at least ``MIN_RANGE``."""
    return expression[:, actions].abs().amax(dim=0).clamp_min(MIN_RANGE)


def expression_sh0(
    sh0: Tensor, offsets: Tensor, coefficients: Tensor, reach: Tensor, scale: Tensor
) -> Tensor:
    """The DC colours under an expression: ``sh0 + sum_k m_k clamp(e_k / r_k, -1, 1) offsets_k``.

    sh0: [N, 1, 3]; offsets: [N, K, 3]; coefficients: [K] (one frame's, of the K actions); reach:
    [N, K] (bool or float) each Gaussian's ``m_k``; scale: [K] ``r_k``. Returns [N, 1, 3]."""
    amount = (coefficients / scale).clamp(-1.0, 1.0).to(offsets.dtype)
    weights = reach.to(offsets.dtype) * amount[None, :]  # [N, K]
    return sh0 + torch.einsum("nk,nkc->nc", weights, offsets)[:, None, :]


@torch.no_grad()
def clamp_offsets(offsets: Tensor) -> None:
    """Project every offset into [-MAX_OFFSET, MAX_OFFSET] (in place, so the optimizer keeps its
    state): Adam moves a rarely used action's offsets at full rate whatever its gradient's size,
    and no colour needs more than the whole range."""
    offsets.clamp_(-MAX_OFFSET, MAX_OFFSET)
