"""``eva preprocess``: a video of one person -> a dataset ``eva train`` reads."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app
from eva_engine.cli.progress import stage_bars


@app.command()
def preprocess(
    video: Path = typer.Argument(..., help="Video file (mp4, mov, webm, avi, ...)."),
    out: Path = typer.Option(..., "--out", "-o", help="Dataset folder to write."),
    every: int = typer.Option(1, min=1, help="Keep every k-th frame."),
    max_frames: int = typer.Option(300, min=1, help="Stop after this many kept frames."),
    max_size: int = typer.Option(512, min=64, max=4096, help="Longest image side in pixels."),
    detect_max_size: int = typer.Option(
        1280, min=64, max=8192, help="Longest side of the frames the detector sees (more pixels for hands)."
    ),
    fov: float = typer.Option(55.0, min=5.0, max=150.0, help="Guessed vertical field of view (degrees)."),
    test_every: int = typer.Option(0, min=0, help="Every k-th frame goes to the test split (0: none)."),
    fit: bool = typer.Option(True, "--fit/--no-fit", help="Align the body model to the detections."),
    face_crops: bool = typer.Option(
        True,
        "--face-crops/--no-face-crops",
        help="Store face close-ups at the video's resolution (when it is larger than --max-size).",
    ),
    overwrite: bool = typer.Option(False, help="Replace an existing dataset at --out."),
) -> None:
    """Decode, detect body/hands/face (MediaPipe), fit the body model (EVA §3.2), write a dataset."""

    from eva_engine.align import PreprocessConfig, PreprocessError, preprocess_video
    from eva_engine.data import VideoError
    from eva_engine.data.face_crops import FaceCropConfig

    console = Console(stderr=True)
    if test_every == 1:
        raise typer.BadParameter("use 0 (no test frames) or >= 2", param_hint="--test-every")
    if out.exists() and not overwrite:
        console.print(f"[red]error:[/] {out} exists (pass --overwrite to replace a dataset)")
        raise typer.Exit(2)
    config = PreprocessConfig(
        every=every,
        max_frames=max_frames,
        max_size=max_size,
        detect_max_size=detect_max_size,
        fov_y_deg=fov,
        test_every=test_every,
        fit=fit,
        face_crops=FaceCropConfig() if face_crops else None,
    )
    with stage_bars(console) as report:
        try:
            result = preprocess_video(video, out, config, progress=report, overwrite=overwrite)
        except (VideoError, PreprocessError, FileExistsError) as err:
            console.print(f"[red]error:[/] {err}")
            raise typer.Exit(2) from err
    console.print(json.dumps(result.to_json(), indent=1))
    counts = f"{result.kept_frames} frames ({result.dropped_frames} without a person dropped)"
    console.print(f"[green]wrote[/] {result.dataset}: {counts}")
