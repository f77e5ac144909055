"""``eva render``: one still of an avatar in a pose (the API's pose and camera JSON) to an image."""

from __future__ import annotations

import re
import time
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app
from eva_engine.cli.parsing import background_value, camera_value, json_value, validation_message

_FRAME = re.compile(r"^frame:(\d+)$")


@app.command()
def render(
    avatar: Path = typer.Argument(..., help="Avatar directory (from `eva train` or the service)."),
    out: Path = typer.Option(..., "--out", "-o", help="Image to write (.png or .jpg)."),
    pose: str = typer.Option(
        "rest",
        help="Pose JSON (a file or inline, the API's BodyPose), `frame:N` for training frame N's "
        "fitted pose and camera, or `rest`.",
    ),
    camera: str | None = typer.Option(
        None,
        help="A preset (front, back, left, right, front_left, front_right, above) or a camera as "
        "JSON (file or inline: orbit yaw/pitch/distance/target/fov_y, K and viewmat, or "
        '{"frame": N, "yaw": 35}: training frame N\'s camera relative to the body, turned by yaw/pitch).',
    ),
    width: int | None = typer.Option(None, min=16, max=4096, help="Pixels (default 512, or the frame's)."),
    height: int | None = typer.Option(None, min=16, max=4096, help="Pixels (default 512, or the frame's)."),
    background: str = typer.Option("white", help="white, black, grey, #rrggbb or r,g,b in [0, 1]."),
    framed: bool = typer.Option(
        True,
        "--framed/--origin",
        help="Aim an orbit camera that sets no target/distance at the avatar's "
        "Gaussians (--origin: the API's default, the world origin from 2.6 m).",
    ),
) -> None:
    """Render the avatar in a pose, expression and view: the same JSON as `POST /avatars/{id}/render`.
    A pose or view beyond what the training video showed is rendered with a warning saying so."""
    from PIL import Image
    from pydantic import ValidationError

    from eva_engine.avatar import AvatarFileError, RenderInputError, load_saved_avatar
    from eva_engine.avatar.framing import framed_camera
    from eva_engine.avatar.render_spec import (
        RenderSpec,
        coverage_warnings,
        render_image,
        resolve_size,
        spec_camera,
        spec_params,
    )
    from eva_engine.body import InvalidPoseError

    console = Console(stderr=True)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise typer.BadParameter(f"the output must be .png or .jpg, got {out.name}", param_hint="--out")
    doc: dict = {"background": background_value(background)}
    if match := _FRAME.match(pose.strip()):
        doc["frame"] = int(match.group(1))
    elif pose.strip() != "rest":
        doc["pose"] = json_value(pose, "pose", "--pose")
    if (cam := camera_value(camera)) is not None:
        doc["camera"] = cam
    doc.update({k: v for k, v in (("width", width), ("height", height)) if v is not None})
    try:
        spec = RenderSpec.model_validate(doc)
    except ValidationError as err:
        console.print(f"[red]error:[/] {validation_message(err)}")
        raise typer.Exit(2) from err
    started = time.perf_counter()
    try:
        saved = load_saved_avatar(avatar)
    except AvatarFileError as err:
        console.print(f"[red]error:[/] {err}")
        raise typer.Exit(2) from err
    model, frames = saved.avatar.eval(), saved.frames
    if framed and not (spec.frame is not None and spec.camera is None):  # a training frame's own camera
        w, h = resolve_size(spec, frames)
        spec = spec.model_copy(update={"camera": framed_camera(model, spec.camera, w, h)})
    try:
        w, h = resolve_size(spec, frames)
        params = spec_params(model, spec, frames)
        cam = spec_camera(spec, w, h, frames, model, params)
    except (InvalidPoseError, RenderInputError) as err:
        console.print(f"[red]error:[/] {err}")
        raise typer.Exit(2) from err
    image = render_image(model, params, cam, spec.background)
    for warning in coverage_warnings(saved.meta.coverage, model, spec, params, cam):
        console.print(f"[yellow]warning:[/] {warning}", highlight=False)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(out, **({} if out.suffix.lower() == ".png" else {"quality": 92}))
    h, w = image.shape[:2]
    console.print(f"[green]wrote[/] {out} ({w}x{h}, {time.perf_counter() - started:.1f} s)")
