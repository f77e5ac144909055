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
    width: int = typer.Option(384, min=16, max=4096, help="Width of each view in pixels."),
    height: int = typer.Option(512, min=16, max=4096, help="Height in pixels."),
) -> None:
    """Pose the embedded Anny body, render it as 3D Gaussians from two views, write a PNG."""
    import numpy as np
    from PIL import Image

    from eva_engine.body import load_body_model
    from eva_engine.demo import render_demo

    console = Console(stderr=True)
    if out.suffix.lower() != ".png":
        raise typer.BadParameter(f"the output must be a .png file, got {out}", param_hint="--out")
    started = time.perf_counter()
    model = load_body_model("anny")
    image = render_demo(model, width=width, height=height)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((image.numpy() * 255 + 0.5).astype(np.uint8)).save(out)
    size = f"{image.shape[1]}x{image.shape[0]}"
    console.print(f"[green]wrote[/] {out} ({size}, {time.perf_counter() - started:.1f} s)")
