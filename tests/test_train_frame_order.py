"""The training frames' order (``train/frame_order.py``): every frame once per epoch as before,
and the frames of a rare expression repeated when asked."""

from __future__ import annotations

import pytest
import torch

from eva_engine.train.frame_order import ExpressionEventsConfig, epoch_frames, shuffled

NAMES = ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight"]


def expressions(blinks: dict[int, float], frames: int = 6) -> torch.Tensor:
    e = torch.zeros(frames, len(NAMES))
    for frame, value in blinks.items():
        e[frame, 1 + frame % 2] = value  # left on even frames, right on odd
    return e


def test_without_repeats_every_frame_once_in_the_order_training_drew_before():
    e = expressions({2: 0.9})
    frames = epoch_frames(e, NAMES, ExpressionEventsConfig())
    assert frames == list(range(6))
    a, b = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert shuffled(frames, a) == torch.randperm(6, generator=b).tolist()


def test_frames_past_the_threshold_come_back_repeats_times():
    e = expressions({1: 0.5, 2: 0.15, 4: 0.21})
    frames = epoch_frames(e, NAMES, ExpressionEventsConfig(repeats=2, threshold=0.2))
    assert sorted(frames) == sorted([*range(6), 1, 1, 4, 4])
    assert sorted(shuffled(frames, torch.Generator().manual_seed(0))) == sorted(frames)


def test_actions_the_body_lacks_or_other_actions_add_nothing():
    e = expressions({1: 0.9})
    assert epoch_frames(e, NAMES, ExpressionEventsConfig(repeats=3, actions=("mouthSmile",))) == list(
        range(6)
    )
    jaw = ExpressionEventsConfig(repeats=1, actions=("jawOpen",))
    e[3, 0] = 0.6
    assert epoch_frames(e, NAMES, jaw) == [*range(6), 3]


def test_negative_repeats_are_refused():
    with pytest.raises(ValueError, match="repeats"):
        ExpressionEventsConfig(repeats=-1)
