"""``eva animate``: make an avatar perform the motion of a driving video (or a JSON pose sequence)
and write it as an H.264 mp4."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app
from eva_engine.cli.parsing import background_value, camera_value, validation_message
from eva_engine.cli.progress import stage_bars
from eva_engine.progress import ProgressEvent


@app.command()
def animate(
    avatar: Path = typer.Argument(..., help="Avatar directory (from `eva train` or the service)."),
    driving: Path = typer.Argument(
        ...,
        help="A video of anyone (preprocessed and aligned here), a JSON file of poses "
        '({"fps": 25, "poses": [BodyPose, ...]}), or a dataset folder from `eva preprocess`.',
    ),
    out: Path = typer.Option(..., "--out", "-o", help="The mp4 to write."),
    camera: str = typer.Option(
        "front",
        help="`driving` (the driving video's camera: the avatar where the person was), a preset "
        "(front, left, ...) or an orbit camera as JSON; an orbit without target/distance is framed on the "
        "avatar.",
    ),
    side_by_side: bool = typer.Option(False, "--side-by-side", help="The driving frame | the avatar."),
    fps: float | None = typer.Option(
        None, min=0.1, max=120.0, help="Output frame rate (default: the driving's); the motion is resampled."
    ),
    width: int | None = typer.Option(None, min=16, max=4096, help="Avatar picture width in pixels."),
    height: int | None = typer.Option(None, min=16, max=4096, help="Avatar picture height in pixels."),
    smooth: float = typer.Option(
        0.04, min=0.0, max=2.0, help="Temporal smoothing: standard deviation in seconds (0: off)."
    ),
    background: str = typer.Option("white", help="white, black, grey, #rrggbb or r,g,b in [0, 1]."),
    max_frames: int = typer.Option(300, min=1, help="Driving video: frames used (from the start)."),
    max_size: int = typer.Option(512, min=64, max=4096, help="Driving video: longest image side."),
    fit_scale: float = typer.Option(
        1.0, min=0.01, max=4.0, help="Driving video: scales the body fit's iterations (1 = the paper's)."
    ),
) -> None:
    """Retarget the driving motion onto the avatar (its joint rotations and expressions; the avatar
    keeps its shape, the root's travel scales with height), smooth it, render every frame, encode."""
    from pydantic import ValidationError

    from eva_engine.align import PreprocessConfig, scaled_fit_config
    from eva_engine.animate import (
        AnimationConfig,
        AnimationError,
        DrivingError,
        load_driving,
        write_animation,
    )
    from eva_engine.animate import animate as run_animation
    from eva_engine.avatar import AvatarFileError, load_avatar

    console = Console(stderr=True)
    if out.suffix.lower() != ".mp4":
        raise typer.BadParameter(f"the output must be an .mp4 file, got {out.name}", param_hint="--out")
    doc = {
        "camera": camera_value(camera, allow_driving=True),
        "side_by_side": side_by_side,
        "fps": fps,
        "width": width,
        "height": height,
        "smooth_s": smooth,
        "background": background_value(background),
    }
    try:
        config = AnimationConfig.model_validate(doc)
    except ValidationError as err:
        console.print(f"[red]error:[/] {validation_message(err)}")
        raise typer.Exit(2) from err
    try:
        model = load_avatar(avatar).eval()
    except AvatarFileError as err:
        console.print(f"[red]error:[/] {err}")
        raise typer.Exit(2) from err
    fitting = scaled_fit_config(fit_scale)
    # A driving video gives motion, not appearance: no face close-ups.
    preprocess = PreprocessConfig(max_frames=max_frames, max_size=max_size, fitting=fitting, face_crops=None)
    started = time.perf_counter()
    with stage_bars(console) as report:
        try:
            motion = load_driving(driving, model.body, preprocess, progress=report)
            result = run_animation(model, motion, config, progress=report)
        except (DrivingError, AnimationError) as err:
            console.print(f"[red]error:[/] {err}")
            raise typer.Exit(2) from err
        report(ProgressEvent("encode", 0, 1))
        write_animation(out, result)
        report(ProgressEvent("encode", 1, 1))
    h, w = result.frames.shape[1:3]
    dropped = f", {motion.dropped} driving frames without a person skipped" if motion.dropped else ""
    console.print(
        f"[green]wrote[/] {out}: {len(result)} frames {w}x{h} at {result.fps:g} fps{dropped} "
        f"({time.perf_counter() - started:.1f} s)"
    )
