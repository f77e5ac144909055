"""Which training frame each step sees (``train/frame_order.py``)."""

from __future__ import annotations

import pytest
import torch

from eva_engine.body import expression_group_masks
from eva_engine.train.config import TrainConfig
from eva_engine.train.frame_order import FrameOrder, expression_rarity


def test_uniform_order_is_the_seeded_permutation_epoch_by_epoch():
    order = FrameOrder(torch.zeros(5, 3), 0.0, torch.Generator().manual_seed(7))
    reference = torch.Generator().manual_seed(7)
    expected = (
        torch.randperm(5, generator=reference).tolist()[::-1]
        + torch.randperm(5, generator=reference).tolist()[::-1]
    )
    assert [order.next() for _ in range(10)] == expected  # as the trainer drew frames before
    assert torch.allclose(order.probabilities, torch.full((5,), 0.2, dtype=torch.float64))


def test_rare_expressions_are_drawn_more_often():
    expression = torch.zeros(20, 4)
    expression[3, 1] = 1.0  # one blink among 20 neutral frames
    rarity = expression_rarity(expression)
    assert rarity[3] == pytest.approx(20.0) and rarity.sum() == pytest.approx(20.0)
    order = FrameOrder(expression, 1.0, torch.Generator().manual_seed(0))
    assert order.probabilities[3] == pytest.approx(21 / 40)  # weights 1 + rarity: 21 against 19 x 1
    draws = torch.tensor([order.next() for _ in range(4000)])
    assert (draws == 3).float().mean() == pytest.approx(21 / 40, abs=0.03)
    assert set(draws.tolist()) == set(range(20))  # every frame is still seen


def test_degenerate_expressions_and_strengths():
    same = FrameOrder(torch.ones(4, 2), 5.0, torch.Generator().manual_seed(0))
    assert torch.allclose(same.probabilities, torch.full((4,), 0.25, dtype=torch.float64))
    assert torch.equal(expression_rarity(torch.zeros(3, 0)), torch.zeros(3))  # a body model without a face
    huge = FrameOrder(torch.tensor([[0.0], [0.0], [1e30]]), 100.0, torch.Generator().manual_seed(0))
    assert torch.isfinite(huge.probabilities).all() and huge.next() in (0, 1, 2)
    with pytest.raises(ValueError, match="strength"):
        FrameOrder(torch.zeros(2, 1), -1.0, torch.Generator())
    with pytest.raises(ValueError, match="expression_sampling"):
        TrainConfig(expression_sampling=101.0)


def test_a_blink_is_rare_among_the_lids_while_the_mouth_talks():
    names = ["jawOpen", "mouthClose", "eyeBlinkLeft", "eyeBlinkRight", "browInnerUp"]
    masks = expression_group_masks(names)
    assert [m.tolist() for m in masks] == [
        [True, False, False, False, False],
        [False, True, False, False, False],
        [False, False, True, True, False],
        [False, False, False, False, True],
    ]
    gen = torch.Generator().manual_seed(0)
    expression = torch.zeros(30, 5)
    expression[:, :2] = torch.rand(30, 2, generator=gen)  # talking: jaw and lips never rest
    expression[7, 2:4] = 0.8  # one blink
    grouped = expression_rarity(expression, masks)
    assert int(grouped.argmax()) == 7 and grouped[7] > 10
    assert grouped[7] > 2 * expression_rarity(expression)[7]  # as one group, the talk hides it
    # SMPL-X's PCA expressions match no group: one group of everything.
    assert [m.tolist() for m in expression_group_masks(["expr_0", "expr_1"])] == [[True, True]]
