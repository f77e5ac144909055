"""``serve(settings)``: the app under uvicorn with the settings' connection limits (``eva serve``)."""

from __future__ import annotations

import gc
import sys

from service.app import create_app
from service.connections import guarded_protocol
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
        # No cap on connections in uvicorn: it would answer 503 to every request, /healthz too,
        # while idle sockets hold it. Waiting connections are bounded by the protocol instead,
        # requests in flight by the guard (503 with Retry-After).
        http=guarded_protocol(settings.connections),
        limit_concurrency=None,
        timeout_keep_alive=5,
        server_header=False,
    )
