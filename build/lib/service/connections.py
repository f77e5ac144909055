"""``guarded_protocol(limits)``: uvicorn's HTTP/1.1 protocol with limits on connections that wait.

A connection *waits* from when it opens, and again from the end of each response, until the
headers of its next request have arrived. Waiting connections cost the server nothing but a
socket, which is why an attacker without a key can hold hundreds of them; the request guard
(``service.guard``) never sees them, since it runs only once headers have arrived. So here:

- a connection that waits longer than ``header_timeout_s`` is closed (slow or silent headers);
- when a client address holds more than ``max_waiting_per_client`` connections that have sent
  nothing yet, or the server more than ``max_waiting``, a new one closes the *oldest* of them (of
  that client first): idle sockets can never lock out a client that sends its request at once.
  A keep-alive connection between two requests is left to uvicorn's keep-alive timeout: closing
  it would race its client's next request. The caps are loose (128 from one address): behind a
  reverse proxy every client has its address, and the 50 clients of ``bench/serving.py load``,
  from one address and starved of CPU between connecting and sending, lost requests to a cap
  of 16.

Connections with a request in flight are not counted: ``RequestGuard`` bounds those (503 with
``Retry-After``), and ``/healthz`` passes it. A reverse proxy in front (``docs/deployment.md``)
adds what belongs there: TLS, per-address rates, larger floods.
"""

from __future__ import annotations

import logging
import time

from pydantic import BaseModel, ConfigDict, Field
from uvicorn.protocols.http.h11_impl import H11Protocol

logger = logging.getLogger("eva.service")


class ConnectionLimits(BaseModel):
    """header_timeout_s: longest wait for a request's headers (from the connection's opening or
    the previous response's end); max_waiting_per_client / max_waiting: waiting connections of
    one client address / of all (past either, a new connection closes the oldest waiting)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    header_timeout_s: float = Field(10.0, gt=0)
    max_waiting_per_client: int = Field(128, ge=1)
    max_waiting: int = Field(512, ge=1)


def guarded_protocol(limits: ConnectionLimits) -> type[H11Protocol]:
    """uvicorn's h11 protocol class with ``limits`` (pass it as ``uvicorn.run(http=...)``)."""

    class GuardedH11Protocol(H11Protocol):
        _limits = limits
        _header_timer = None
        _waiting_since = 0.0

        def connection_made(self, transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._start_waiting()
            self._shed_waiting()

        def on_response_complete(self) -> None:
            self._start_waiting()  # before super(): it may start a pipelined request at once
            super().on_response_complete()

        def connection_lost(self, exc: Exception | None) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None
            super().connection_lost(exc)

        @property
        def waiting(self) -> bool:
            """No request of this connection is between its headers and its response's end."""
            return not self.transport.is_closing() and (self.cycle is None or self.cycle.response_complete)

        def _start_waiting(self) -> None:
            self._waiting_since = time.monotonic()
            if self._header_timer is None:
                self._header_timer = self.loop.call_later(self._limits.header_timeout_s, self._check_headers)

        def _check_headers(self) -> None:
            self._header_timer = None
            if not self.waiting:  # a request is in flight; on_response_complete starts the clock again
                return
            left = self._waiting_since + self._limits.header_timeout_s - time.monotonic()
            if left > 0:  # waiting again since a later response
                self._header_timer = self.loop.call_later(left, self._check_headers)
                return
            self._close("no request headers within %.0f s", self._limits.header_timeout_s)

        @property
        def fresh(self) -> bool:
            """Waiting, and no request yet: an idle keep-alive connection between a client's
            requests is not shed (its client may be sending on it right now; uvicorn's keep-alive
            timeout closes it)."""
            return self.waiting and self.cycle is None

        def _shed_waiting(self) -> None:
            waiting = [c for c in self.connections if isinstance(c, GuardedH11Protocol) and c.fresh]
            mine = [c for c in waiting if c.client_host == self.client_host]
            caps = self._limits.max_waiting_per_client, self._limits.max_waiting
            for group, cap in zip((mine, waiting), caps, strict=True):
                if len(group) > cap:
                    oldest = min(group, key=lambda c: c._waiting_since)
                    oldest._close("more than %d waiting connections", cap)
                    return

        @property
        def client_host(self) -> str | None:
            return self.client[0] if self.client else None

        def _close(self, why: str, *args) -> None:
            logger.debug("closing a connection from %s: " + why, self.client_host, *args)
            self.transport.close()

    return GuardedH11Protocol
