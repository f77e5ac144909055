"""The teacher scene the avatar tests train on (``helpers/scenes.py``) is a fair scene."""

from __future__ import annotations

import torch
from helpers.scenes import teacher_scene


def test_teacher_scene_is_a_fair_scene(anny_model):
    ds, teacher = teacher_scene(anny_model, n_frames=4, size=48)
    assert ds.splits["test_pose"] == [2] and ds.splits["train"] == [0, 1, 3]
    for i in range(len(ds)):
        f = ds[i]
        assert 0.05 < float((f.mask > 0.5).float().mean()) < 0.6  # the person fills part of the view
        assert all(m.sum() > 0 for m in f.regions.values()), "both hands and the face in view"
        for m in f.regions.values():
            assert torch.all(m <= (f.mask > 0.3).float())
        # each hand's mask lies on its own side of the image (the subject's left is image right)
        cols = torch.arange(f.mask.shape[1]).float()
        hands = ("hand_left", "hand_right")
        centre = {h: float((f.regions[h].sum(0) * cols).sum() / f.regions[h].sum()) for h in hands}
        assert centre["hand_left"] > centre["hand_right"]
    # Poses differ, so test frames are novel poses.
    assert not torch.allclose(ds[0].image, ds[1].image)
