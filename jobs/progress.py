"""Job progress from the engine's progress events: the engine's preprocessing stages mapped onto
the job's stages, shared by avatar and animation jobs."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from eva_engine.progress import Progress, ProgressEvent

# Each stage of ``preprocess_video`` as a part of a job stage: (job stage, from, to), fractions.
PREPROCESS_SPANS = {
    "decode": ("preprocess", 0.1, 0.1),
    "detect": ("preprocess", 0.1, 1.0),
    "align": ("align", 0.0, 0.7),
    "regions": ("align", 0.8, 0.8),
    "write": ("align", 0.8, 1.0),
}
# Reported however recent the last report: they start long steps.
FORCED = ("align", "regions")


def preprocess_progress(report: Callable[..., None], fitted: str = "") -> Progress:
    """The ``progress`` of ``preprocess_video`` as job progress (``PREPROCESS_SPANS``): decoding
    and detection are the ``preprocess`` stage; the fit, the region masks and writing the frames
    the ``align`` stage. ``fitted`` ends the fitting message (e.g. " to the driving video").
    ``report(event, force=...)``: a ``jobs.pipeline.Reporter``."""

    def progress(event: ProgressEvent) -> None:
        stage, start, end = PREPROCESS_SPANS[event.stage]
        job_event = event.rescaled(stage, start, end)
        if event.stage == "align":
            job_event = dataclasses.replace(job_event, message=f"{event.message}{fitted}")
        report(job_event, force=event.stage in FORCED)

    return progress
