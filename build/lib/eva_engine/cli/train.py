"""``eva train``: fit a Gaussian avatar to a dataset and write the avatar directory."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app
from eva_engine.recipes import METHODS, PRESETS, describe_methods, describe_presets


@app.command()
def train(
    dataset: Path = typer.Argument(
        ..., help="Dataset folder (eva-dataset layout, see docs/dataset-format.md)."
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Avatar directory to write."),
    preset: str = typer.Option("default", help=f"Training preset: {describe_presets()}."),
    method: str | None = typer.Option(None, help=f"Method: {describe_methods()}; default: the preset's."),
    iterations: int | None = typer.Option(None, min=1, help="Override the preset's iteration count."),
    image_scale: float | None = typer.Option(None, min=0.05, max=4.0, help="Resample frames by this factor."),
    device: str = typer.Option("cpu", help="cpu or cuda."),
    threads: int | None = typer.Option(None, min=1, help="Torch CPU threads."),
    seed: int = typer.Option(0, help="Random seed (runs on one thread are bit-identical given it)."),
    quality: bool = typer.Option(
        True, help="Score the avatar on the dataset's held-out frames and keep the report in avatar.json."
    ),
    settings: list[str] = typer.Option(
        [],
        "--set",
        help="A training-config field, dotted, its value as JSON (e.g. loss.lambda_ssim=0.01); repeat "
        "for more. Applied after --preset and --method; avatar.json's train_config keeps the result.",
    ),
) -> None:
    """Train an avatar on the dataset's training frames (EVA: 2,000 iterations), then score it on
    the frames it did not train on (its quality report)."""
    import torch
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from eva_engine.avatar import save_avatar
    from eva_engine.data import DatasetError, load_dataset
    from eva_engine.progress import ProgressEvent
    from eva_engine.train import TrainingError, train_avatar, with_method, with_overrides
    from eva_engine.train import preset as make_preset

    console = Console(stderr=True)
    if preset not in PRESETS:
        raise typer.BadParameter(
            f"unknown preset {preset!r}; choose one of {list(PRESETS)}", param_hint="--preset"
        )
    if method is not None and method not in METHODS:
        raise typer.BadParameter(
            f"unknown method {method!r}; choose one of {list(METHODS)}", param_hint="--method"
        )
    if not dataset.is_dir():
        console.print(f"[red]error:[/] no dataset folder at {dataset}")
        raise typer.Exit(2)
    try:
        ds = load_dataset(dataset)
    except DatasetError as err:
        console.print(f"[red]error:[/] {err}")
        raise typer.Exit(2) from err
    if threads is not None:  # this process's, set once here (a training run leaves them alone)
        torch.set_num_threads(threads)
    overrides: dict = {"device": device, "seed": seed}
    if iterations is not None:
        overrides["iterations"] = iterations
    if image_scale is not None:
        overrides["image_scale"] = image_scale
    config = make_preset(preset, **overrides)
    if method is not None:
        config = with_method(config, method)
    try:
        config = with_overrides(config, settings)
    except (ValueError, TypeError) as err:
        raise typer.BadParameter(str(err), param_hint="--set") from err

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TextColumn("loss {task.fields[loss]:.4f}"),
        TextColumn("{task.fields[gaussians]} GS"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    started = time.perf_counter()
    with Progress(*columns, console=console, transient=False) as bar:
        task = bar.add_task("setup", total=config.iterations, loss=float("nan"), gaussians=0)

        def report(event: ProgressEvent) -> None:
            loss = event.loss if event.loss is not None else float("nan")
            bar.update(
                task,
                description=event.stage,
                completed=event.done,
                loss=loss,
                gaussians=event.num_gaussians or 0,
            )

        try:
            result = train_avatar(ds, config, progress=report)
        except TrainingError as err:
            console.print(f"[red]error:[/] {err}")
            raise typer.Exit(2) from err
    report_doc = None
    if quality:
        from eva_engine.eval import quality_report

        report_doc = quality_report(result.avatar, ds)
    record = result.record(
        config,
        preset=preset,
        method=method,
        dataset=str(dataset.resolve()),
        quality=report_doc.model_dump() if report_doc is not None else None,
    )
    # Training poses (as trained) and cameras: `eva render --pose frame:N`.
    save_avatar(result.avatar, out, record, frames=result.frames(ds))
    console.print(
        f"[green]wrote[/] {out}: {len(result.avatar.gaussians):,} Gaussians, "
        f"{config.iterations} iterations in {result.train_seconds:.1f} s "
        f"(total {time.perf_counter() - started:.1f} s)"
    )
    held = report_doc.held_out if report_doc is not None else None
    if held is not None:
        lpips = held.lpips_vgg * 1000 if held.lpips_vgg is not None else None
        scores = {"PSNR": held.psnr, "LPIPS-VGG ×1000": lpips, "silhouette IoU": held.silhouette_iou}
        shown = ", ".join(f"{k} {v:.3g}" for k, v in scores.items() if v is not None)
        console.print(f"held-out frames ({held.frames}, poses it never trained on): {shown}")
    elif quality:
        console.print("no held-out frames in this dataset: nothing to score the avatar on unseen poses")
    if report_doc is not None and report_doc.verdict is not None:
        colour = {"good": "green", "fair": "yellow", "poor": "red"}[report_doc.verdict]
        console.print(f"quality: [{colour}]{report_doc.verdict}[/]")
        for reason in report_doc.reasons:
            console.print(f"  - {reason}")
