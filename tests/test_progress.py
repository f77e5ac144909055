"""``ProgressEvent``, the one progress type: its fraction and rescaling, the job's mapping of the
engine's preprocessing stages, and the command line's bars."""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from eva_engine.cli.progress import stage_bars
from eva_engine.progress import ProgressEvent
from jobs.progress import preprocess_progress


def test_fraction_and_rescaled():
    assert ProgressEvent("detect", 3, 12).fraction == 0.25
    assert ProgressEvent("detect", 3, 0).fraction == 0.0  # total unknown
    assert ProgressEvent("fit", 15, 10).fraction == 1.0  # line searches overshoot the iterations
    event = ProgressEvent("train", 50, 100, "iteration 50/100", loss=0.1, num_gaussians=7, eta=3.0)
    part = event.rescaled("train", 0.0, 0.95)
    assert part.fraction == pytest.approx(0.475) and part.stage == "train"
    assert (part.message, part.loss, part.num_gaussians, part.eta) == ("iteration 50/100", 0.1, 7, 3.0)


def test_preprocessing_as_job_progress():
    """Decoding and detection are the job's preprocess stage; fitting, regions, writing and the
    face close-ups its align stage, with the messages a client sees."""
    seen = []

    def report(event: ProgressEvent, force: bool = False) -> None:
        seen.append((event.stage, event.fraction, event.message, force))

    progress = preprocess_progress(report, fitted=" to the driving video")
    for event in (
        ProgressEvent("decode", 40, 40, "decoded 40 frames"),
        ProgressEvent("detect", 20, 40, "detecting the person: frame 20/40"),
        ProgressEvent("align", 0, 3, "fitting the body model"),
        ProgressEvent("regions", 40, 40, "rendering hand and face regions"),
        ProgressEvent("write", 40, 40, "writing frame 40/40"),
        ProgressEvent("face_crops", 40, 40, "40 face close-ups"),
    ):
        progress(event)
    expected = [
        ("preprocess", 0.1, "decoded 40 frames", False),
        ("preprocess", 0.55, "detecting the person: frame 20/40", False),
        ("align", 0.0, "fitting the body model to the driving video", True),
        ("align", 0.8, "rendering hand and face regions", True),
        ("align", 0.95, "writing frame 40/40", False),
        ("align", 1.0, "40 face close-ups", False),
    ]
    assert [(s, pytest.approx(f), m, force) for s, f, m, force in expected] == seen


def test_stage_bars_show_every_stage():
    out = io.StringIO()
    with stage_bars(Console(file=out, width=100, force_terminal=False)) as report:
        report(ProgressEvent("detect", 5, 10))
        report(ProgressEvent("detect", 10, 10))
        report(ProgressEvent("render", 2, 0))  # total unknown
    text = out.getvalue()
    assert "detect" in text and "10/10" in text and "render" in text
