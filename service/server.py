"""``serve(settings)``: the app under uvicorn with the settings' connection limits (``eva serve``)."""

from __future__ import annotations

import gc
import sys

from service.app import create_app
from service.settings import ServiceSettings


def serve(settings: ServiceSettings, log_level: str = "info") -> None:
    import uvicorn

    # Render threads run Python between torch ops: hand the GIL over every 1 ms (not 5) so the
    # event loop answers (/healthz, 503s) while they work.
    sys.setswitchinterval(0.001)
    app = create_app(settings)
    # Imports leave ~10^5 long-lived objects: out of the collector's sight, a full collection
    # no longer pauses every request for tens of milliseconds.
    gc.collect()
    gc.freeze()
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        # Behind the guard's 503s (which say Retry-After), uvicorn's own cap on connections.
        limit_concurrency=2 * settings.max_requests,
        timeout_keep_alive=5,
        server_header=False,
    )
