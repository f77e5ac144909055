"""The web page at ``/``: plain HTML, JavaScript and CSS from ``service/static`` (no build step, no
CDN: the service runs offline). The page holds no secret, so it is served without the API key; it
asks for the key when the API answers 401 and sends it with every call."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"

router = APIRouter(include_in_schema=False)


@router.get("/")
def index() -> FileResponse:
    headers = {"Cache-Control": "no-cache"}  # a new version of the service shows its new page at once
    return FileResponse(STATIC_DIR / "index.html", media_type="text/html", headers=headers)
