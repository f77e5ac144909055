"""The synthetic benchmark's presets and sizes by name, the one list of each: ``eva_engine.synth``
defines them (``benchmark.PRESETS``, ``benchmark.SIZES``); ``eva synth`` and the bench scripts offer
exactly these.

Plain data: reading it imports no torch (``eva_engine.synth`` does), so ``eva --help`` starts
without it.
"""

from __future__ import annotations

SYNTH_PRESETS: dict[str, str] = {
    "controlled": "XHumans-like, thighs up, ground truth given, tested on other motion takes",
    "wild": "UPB-like waist-up signer, alternate frames tested",
    "wild-gt": "wild's framing and split, ground truth given (the paper's regime)",
    "novel": "controlled's subject trained with the arms low; tested on raised arms and 35/70 deg views",
}
"""Preset name -> what it shows."""

SYNTH_SIZES: dict[str, str] = {
    "tiny": "96 px",
    "small": "256 px, 12 training frames",
    "bench": "512 px, 150 training frames",
}
"""Size name -> its resolution and length."""


def describe_synth_presets() -> str:
    """The presets in words, for help texts: ``controlled: XHumans-like, ...; wild: ...``."""
    return "; ".join(f"{name}: {what}" for name, what in SYNTH_PRESETS.items())


def describe_synth_sizes() -> str:
    """The sizes in words, for help texts: ``tiny: 96 px; small: ...``."""
    return "; ".join(f"{name}: {what}" for name, what in SYNTH_SIZES.items())
