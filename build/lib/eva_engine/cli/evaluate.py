"""``eva eval``: evaluate an avatar on a dataset's novel-pose frames (paper Table 1 metrics)."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app


@app.command("eval")
def evaluate(
    avatar_dir: Path = typer.Argument(..., help="Avatar directory written by `eva train`."),
    dataset: Path = typer.Argument(..., help="Dataset folder with the test frames."),
    json_out: Path | None = typer.Option(None, "--json", help="Write the metrics as JSON here."),
    split: str = typer.Option(
        "test_pose",
        help="Split to evaluate: test_pose, test_view, test_far_pose or test_far_view (the last two: "
        "the synthetic `novel` preset's poses beyond the training range).",
    ),
    name: str | None = typer.Option(None, help="Row name in the table (default: the avatar folder)."),
    refine_poses: int = typer.Option(
        0,
        "--refine-poses",
        min=0,
        help="Second protocol: refine each test frame's pose for this many steps against its image, "
        "the avatar frozen, before scoring (0: the fitted poses, the main protocol).",
    ),
) -> None:
    """PSNR / SSIM / LPIPS on full image, hands and face; debris and holes of the silhouette;
    Gaussian count, training time, FPS."""
    from eva_engine.avatar import AvatarFileError, load_saved_avatar
    from eva_engine.data import DatasetError, load_dataset
    from eva_engine.eval import PoseRefinement, evaluate_avatar, metrics_table

    console = Console(stderr=True)
    try:
        saved = load_saved_avatar(avatar_dir)
    except AvatarFileError as err:
        console.print(f"[red]error:[/] {err}")
        raise typer.Exit(2) from err
    if not dataset.is_dir():
        console.print(f"[red]error:[/] no dataset folder at {dataset}")
        raise typer.Exit(2)
    try:
        ds = load_dataset(dataset)
        refinement = PoseRefinement(steps=refine_poses) if refine_poses else None
        result = evaluate_avatar(
            saved.avatar, ds, split=split, train_seconds=saved.meta.train_seconds, refinement=refinement
        )
    except (DatasetError, ValueError) as err:
        console.print(f"[red]error:[/] {err}")
        raise typer.Exit(2) from err
    table = metrics_table({name or avatar_dir.name: result})
    typer.echo(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        doc = {"avatar": str(avatar_dir), "dataset": str(dataset), **result.to_dict(), "table": table}
        json_out.write_text(json.dumps(doc, indent=2))
        console.print(f"[green]wrote[/] {json_out}")
