"""Job progress from the engine's preprocessing callbacks, shared by avatar and animation jobs."""

from __future__ import annotations

from collections.abc import Callable


def preprocess_progress(report: Callable[..., None], fitted: str = "") -> Callable[[str, int, int], None]:
    """The ``progress(stage, done, total)`` callback of ``preprocess_video`` as job progress:
    decoding and detection are the ``preprocess`` stage; the fit (to 70%), the region masks (80%)
    and writing the frames (to 100%) the ``align`` stage. ``fitted`` ends the fitting message
    (e.g. " to the driving video"). ``report(stage, fraction, message=..., force=...)``."""

    def progress(stage: str, done: int, total: int) -> None:
        frac = done / max(total, 1)
        if stage == "decode":
            report("preprocess", 0.1, message=f"decoded {done} frames")
        elif stage == "detect":
            report("preprocess", 0.1 + 0.9 * frac, message=f"detecting the person: frame {done}/{total}")
        elif stage == "align":
            report("align", 0.7 * frac, message=f"fitting the body model{fitted}", force=True)
        elif stage == "regions":
            report("align", 0.8, message="rendering hand and face regions", force=True)
        else:
            report("align", 0.8 + 0.2 * frac, message=f"writing frame {done}/{total}")

    return progress
