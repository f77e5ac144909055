"""Job progress from the engine's progress events: the engine's preprocessing stages mapped onto
the job's stages, shared by avatar and animation jobs."""

from __future__ import annotations

import dataclasses
from typing import Protocol

from eva_engine.progress import Progress, ProgressEvent

# Each stage of ``preprocess_video`` as a part of a job stage: (job stage, from, to), fractions.
PREPROCESS_SPANS = {
    "decode": ("preprocess", 0.1, 0.1),
    "detect": ("preprocess", 0.1, 1.0),
    "align": ("align", 0.0, 0.7),
    "regions": ("align", 0.8, 0.8),
    "write": ("align", 0.8, 0.95),
    "face_crops": ("align", 0.95, 1.0),
}
# Reported however recent the last report: they start long steps.
FORCED = ("align", "regions")


class JobReport(Protocol):
    """A job's progress sink (``jobs.pipeline.Reporter``): records ``event``, throttled unless
    ``force``."""

    def __call__(self, event: ProgressEvent, force: bool = False) -> None: ...


def preprocess_progress(report: JobReport, fitted: str = "") -> Progress:
    """The ``progress`` of ``preprocess_video`` as job progress (``PREPROCESS_SPANS``): decoding
    and detection are the ``preprocess`` stage; the fit, the region masks, writing the frames and
    cutting the face close-ups the ``align`` stage. ``fitted`` ends the fitting message (e.g. " to
    the driving video"). ``report``: a ``jobs.pipeline.Reporter``."""

    def progress(event: ProgressEvent) -> None:
        stage, start, end = PREPROCESS_SPANS[event.stage]
        job_event = event.rescaled(stage, start, end)
        if event.stage == "align":
            job_event = dataclasses.replace(job_event, message=f"{event.message}{fitted}")
        report(job_event, force=event.stage in FORCED)

    return progress
