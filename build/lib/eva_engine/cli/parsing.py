"""Command-line spellings of the API's JSON values, shared by ``eva render`` and ``eva animate``:
a value is inline JSON, the path of a JSON file, or a short name. The JSON itself is validated by
the same pydantic schemas as the API's."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def json_value(text: str, what: str, param: str):
    """``text`` as JSON: inline (starting with ``{`` or ``[``) or the path of a JSON file."""
    stripped = text.strip()
    if stripped.startswith(("{", "[")):
        source, raw = "inline JSON", stripped
    else:
        path = Path(text)
        if not path.is_file():
            message = f"no {what} file {text!r} (give a JSON file or inline JSON)"
            raise typer.BadParameter(message, param_hint=param)
        source, raw = str(path), path.read_text()
    try:
        return json.loads(raw)
    except ValueError as err:
        raise typer.BadParameter(f"{source} is not valid JSON: {err}", param_hint=param) from err


def camera_value(text: str | None, param: str = "--camera", allow_driving: bool = False):
    """``--camera``: a preset name (front, left, ...), ``driving`` (where allowed), or a
    ``CameraSpec`` as inline JSON or a JSON file. Returns what the schema's ``camera`` takes."""
    from eva_engine.specs.camera import CAMERA_PRESETS

    if text is None:
        return None
    if text in CAMERA_PRESETS or (allow_driving and text == "driving"):
        return text
    if text.strip().startswith("{") or Path(text).is_file():
        return json_value(text, "camera", param)
    names = list(CAMERA_PRESETS) + (["driving"] if allow_driving else [])
    message = f"unknown camera {text!r}: give one of {names}, or a camera as JSON"
    raise typer.BadParameter(message, param_hint=param)


_COLOURS = {
    "white": (1.0, 1.0, 1.0),
    "black": (0.0, 0.0, 0.0),
    "grey": (0.5, 0.5, 0.5),
    "gray": (0.5, 0.5, 0.5),
}


def background_value(text: str, param: str = "--background") -> tuple[float, float, float]:
    """``--background``: ``white``, ``black``, ``grey``, ``#rrggbb`` or ``r,g,b`` in [0, 1]."""
    value = text.strip().lower()
    if value in _COLOURS:
        return _COLOURS[value]
    try:
        if value.startswith("#") and len(value) == 7:
            return tuple(int(value[i : i + 2], 16) / 255.0 for i in (1, 3, 5))  # type: ignore[return-value]
        parts = tuple(float(x) for x in value.split(","))
    except ValueError:
        parts = ()
    if len(parts) == 3 and all(0.0 <= x <= 1.0 for x in parts):
        return parts  # type: ignore[return-value]
    raise typer.BadParameter(
        f"{text!r} is not a colour: use white, black, grey, #rrggbb or r,g,b in [0, 1]", param_hint=param
    )


def validation_message(err) -> str:
    """A pydantic ``ValidationError`` as one line per problem: ``where: what``."""
    return "; ".join(f"{'.'.join(str(x) for x in e['loc']) or '(top)'}: {e['msg']}" for e in err.errors())
