"""``eva synth``: render a synthetic benchmark dataset (``eva_engine.synth``)."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import typer

from eva_engine.cli.app import app
from eva_engine.synth_names import SYNTH_PRESETS, SYNTH_SIZES, describe_synth_presets, describe_synth_sizes

# Enums so that typer lists and checks the choices; built from the one list of names.
SynthPreset = StrEnum("SynthPreset", {name: name for name in SYNTH_PRESETS})
SynthSize = StrEnum("SynthSize", {name: name for name in SYNTH_SIZES})


@app.command()
def synth(
    preset: SynthPreset = typer.Option(SynthPreset("wild"), help=f"{describe_synth_presets()}."),
    size: SynthSize = typer.Option(SynthSize("tiny"), help=f"{describe_synth_sizes()}."),
    seed: int = typer.Option(0, min=0, help="Random seed (subject, look and motion)."),
    out: Path | None = typer.Option(
        None, help="Output folder (default: <data dir>/synthetic/<preset>-<size>-seed<seed>)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing dataset at --out."),
) -> None:
    """Render a synthetic signer (textured Anny, mesh rasterizer) with ground truth."""
    import time

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from eva_engine.paths import data_dir

    console = Console(stderr=True)
    target = out or data_dir() / "synthetic" / f"{preset.value}-{size.value}-seed{seed}"
    if target.exists() and not target.is_dir():
        raise typer.BadParameter(f"{target} exists and is not a folder", param_hint="--out")
    if target.exists() and not overwrite:
        raise typer.BadParameter(
            f"{target} already exists (pass --overwrite to replace a dataset)", param_hint="--out"
        )

    from eva_engine.body import AnnyCacheError, load_body_model
    from eva_engine.render.mesh import MeshRenderError
    from eva_engine.synth import generate

    start = time.perf_counter()
    try:
        with console.status("Loading the Anny body model..."):
            model = load_body_model("anny")
        columns = (TextColumn("[bold]rendering"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, console=console) as bar:
            task = bar.add_task("frames", total=None)
            path = generate(
                preset.value,
                size.value,
                seed,
                target,
                model=model,
                overwrite=overwrite,
                progress=lambda event: bar.update(task, completed=event.done, total=event.total),
            )
    except FileExistsError as err:
        raise typer.BadParameter(str(err), param_hint="--out") from err
    except (MeshRenderError, AnnyCacheError) as err:
        console.print(f"[red]error:[/red] {err}")
        raise typer.Exit(1) from err
    console.print(f"wrote {path} in {time.perf_counter() - start:.1f} s")
