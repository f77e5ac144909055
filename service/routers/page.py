"""The web page at ``/``: plain HTML, JavaScript and CSS from ``service/static`` (no build step, no
CDN: the service runs offline). The page holds no secret, so it is served without the API key; it
asks for the key when the API answers 401 and sends it with every call.

The upload form's preset and method choices are written into the page here, from the engine's
registry (``eva_engine.recipes``), so the page offers exactly what the API accepts."""

from __future__ import annotations

from html import escape
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

from eva_engine.recipes import METHODS, PRESETS
from jobs.options import JobOptions

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
PRESET_OPTIONS, METHOD_OPTIONS = "<!-- preset options -->", "<!-- method options -->"

router = APIRouter(include_in_schema=False)


def select_options(choices: dict[str, str], selected: str | None = None) -> str:
    """``<option>`` elements for ``choices`` (value -> what it is)."""
    return "".join(
        f'<option value="{escape(name)}"{" selected" if name == selected else ""}>'
        f"{escape(name)} ({escape(what)})</option>"
        for name, what in choices.items()
    )


@router.get("/")
def index() -> HTMLResponse:
    page = (STATIC_DIR / "index.html").read_text()
    page = page.replace(PRESET_OPTIONS, select_options(PRESETS, JobOptions().preset))
    page = page.replace(METHOD_OPTIONS, select_options({name: m.summary for name, m in METHODS.items()}))
    headers = {"Cache-Control": "no-cache"}  # a new version of the service shows its new page at once
    return HTMLResponse(page, headers=headers)
