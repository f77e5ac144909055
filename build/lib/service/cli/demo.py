"""``eva demo``: the whole product end to end on the embedded default."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.recipes import PRESETS
from service.cli.app import app


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo.png"), "--out", "-o", help="PNG to write."),
    workdir: Path = typer.Option(
        Path("out/demo"), help="Folder for the demo's video, service data, avatar and logs (replaced)."
    ),
    preset: str = typer.Option("fast", help=f"Training preset: {', '.join(PRESETS)}."),
    iterations: int | None = typer.Option(None, min=1, help="Override the preset's iteration count."),
    animation: Path | None = typer.Option(
        None, "--animation", help="Also write this mp4: the avatar performing a video of someone else."
    ),
    fit_scale: float | None = typer.Option(
        None, min=0.01, max=4.0, help="Scale the body fit's iterations (1 = the paper's), for both videos."
    ),
    body_only: bool = typer.Option(
        False, "--body-only", help="Skip the product: render the posed body model as Gaussians (seconds)."
    ),
) -> None:
    """Generate a synthetic signer video (the embedded Anny body), submit it to the service
    (`eva serve` + `eva worker`), follow the job, render a new pose. Writes a PNG: input frame |
    avatar in that pose | avatar in a new pose | the new pose from the side; with --animation, an
    mp4 of the avatar performing a video of someone else."""
    import numpy as np
    from PIL import Image
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    if out.suffix.lower() != ".png":
        raise typer.BadParameter(f"the output must be a .png file, got {out}", param_hint="--out")
    if preset not in PRESETS:
        raise typer.BadParameter(
            f"unknown preset {preset!r}; choose one of {list(PRESETS)}", param_hint="--preset"
        )
    started = time.perf_counter()
    if body_only:
        from eva_engine.body import load_body_model
        from eva_engine.demo import render_demo

        image = render_demo(load_body_model("anny"))
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray((image.numpy() * 255 + 0.5).astype(np.uint8)).save(out)
        console.print(f"[green]wrote[/] {out} ({time.perf_counter() - started:.1f} s)")
        return

    from eva_engine.progress import ProgressEvent
    from service.demo import DemoError, run_service_demo

    if animation is not None and animation.suffix.lower() != ".mp4":
        message = f"the animation must be an .mp4 file, got {animation}"
        raise typer.BadParameter(message, param_hint="--animation")
    options = {"preset": preset} | ({"iterations": str(iterations)} if iterations else {})
    options |= {"fit_scale": str(fit_scale)} if fit_scale else {}
    columns = (
        TextColumn("{task.description:>10}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TextColumn("{task.fields[eta]}"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console) as bar:
        task = bar.add_task("starting", total=1.0, eta="")

        def report(event: ProgressEvent) -> None:
            eta = f"eta {event.eta:.0f} s" if event.eta else ""
            bar.update(task, description=event.stage, completed=event.fraction, eta=eta)

        try:
            result = run_service_demo(workdir, out, options, progress=report, out_mp4=animation)
        except DemoError as err:
            console.print(f"[red]error:[/] {err}")
            raise typer.Exit(1) from err
    console.print(
        f"[green]wrote[/] {out}: avatar {result.avatar_id} ({result.num_gaussians:,} Gaussians) trained and "
        f"rendered through the service in {result.seconds:.0f} s; video, service data and logs in {workdir}."
    )
    if result.animation is not None:
        console.print(f"[green]wrote[/] {result.animation}: the avatar performing a video of someone else")
    phases = " · ".join(f"{name} {sec:.0f} s" for name, sec in result.phases.items())
    console.print(f"time per phase: {phases}")
    service = workdir / "service"
    console.print(
        f"See the avatar in the web page: [bold]eva serve --data-dir {service}[/], then open "
        "[bold]http://127.0.0.1:8000/[/]"
    )
