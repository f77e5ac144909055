"""The error answers the routers document (FastAPI's ``responses=``), each an ``ErrorMessage``."""

from __future__ import annotations

from typing import Any

from service.schemas import ErrorMessage


def error(status: int, description: str) -> dict[int | str, dict[str, Any]]:
    """``{status: ...}``, an ``ErrorMessage`` answer, to merge into a route's ``responses``."""
    return {status: {"model": ErrorMessage, "description": description}}


BUSY = error(503, "Busy or over quota: retry after `Retry-After` seconds")
STILL_RUNNING = error(409, "Its job is still running")
AVATAR_NOT_READY = error(409, "The avatar's job has not succeeded")
UPLOAD = {**error(413, "Upload over the size limit"), **error(507, "The server's disk is full"), **BUSY}
"""What any upload can meet besides its own 422s: the size limit, a full disk, the queue's quota."""
