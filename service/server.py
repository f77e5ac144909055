"""``serve(settings)``: the app under uvicorn with the settings' connection limits (``eva serve``)."""

from __future__ import annotations

from service.app import create_app
from service.settings import ServiceSettings


def serve(settings: ServiceSettings, log_level: str = "info") -> None:
    import uvicorn

    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        # Behind the guard's 503s (which say Retry-After), uvicorn's own cap on connections.
        limit_concurrency=2 * settings.max_requests,
        timeout_keep_alive=5,
        server_header=False,
    )
