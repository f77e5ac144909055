"""The web page at ``/``: plain HTML, JavaScript and CSS from ``service/static`` (no build step, no
CDN: the service runs offline). The page holds no secret, so it and its form options are served
without the API key; it asks for the key when the API answers 401 and sends it with every call.

The page fills its forms' choices and number bounds from ``GET /page/options``
(``service.page_options``), what the API itself checks."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from service.page_options import PageOptions, page_options

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
NO_CACHE = {"Cache-Control": "no-cache"}  # a new version of the service shows its new page at once

router = APIRouter(tags=["page"])


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html", headers=NO_CACHE)


@router.get("/page/options", response_model=PageOptions)
def options() -> PageOptions:
    """What the page's forms offer: each select's choices and default, each number field's bounds
    and default, by form id and field name (the API's own names and checks)."""
    return page_options()
