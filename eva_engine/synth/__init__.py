"""The synthetic benchmark (``eva synth``): a textured Anny subject signing, rendered as a triangle
mesh (not Gaussians) and written in the dataset layout with its ground truth.

- ``benchmark``: the presets, sizes and splits, and ``generate`` (the dataset writer);
- ``motion``: sign-language-like motion, deterministic given a seed;
- ``texture``: the subject's procedural look, baked into Anny's UV atlas;
- ``contact_sheet``: frames of a dataset with face and hand close-ups, to look at;
- ``face_crops``: a dataset's face close-ups (``data.face_crops``), rendered at their own size.
"""

from __future__ import annotations

from eva_engine.synth.benchmark import PRESETS, SIZES, Preset, Size, generate

__all__ = ["PRESETS", "SIZES", "Preset", "Size", "generate"]
