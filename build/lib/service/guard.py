"""``RequestGuard``: an ASGI middleware that decides about a request before the app reads a byte
of its body or routes it, in this order:

1. the API key (``X-API-Key``, compared in constant time: the one key, or each account's) unless
   the path is public (``/healthz``) or open (the web page and its static files, which hold no
   secret): 401. Who called (``accounts.Caller``) goes to ``scope["state"]["caller"]``;
2. a browser's cross-site write (``Sec-Fetch-Site: cross-site``; without a key, also an
   ``Origin`` of another scheme, host or port) on a POST, PUT, PATCH or DELETE, e.g. a web page,
   or another program's page on another loopback port, posting a form to the service: 403;
3. requests in flight over ``max_requests`` (public paths, i.e. ``/healthz``, are always
   answered): 503 with ``Retry-After``;
4. the body limit of the route (``BodyRule``: per method and path pattern, else
   ``default_max_bytes``): 413 at once from ``Content-Length``, or as soon as the streamed body
   crosses it; the rule's own cap on concurrent requests (uploads): 503 with ``Retry-After``;
   a body that pauses longer than ``body_timeout_s`` between chunks, or whose average rate
   falls under ``body_min_rate`` bytes/s once ``body_grace_s`` have passed (a sender of a byte
   now and then would hold an upload slot for ever): 408.

A body cut off by 413 or 408 fails the app's parsing, so the endpoint never runs (no half job).
"""

from __future__ import annotations

import asyncio
import re
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from starlette.exceptions import HTTPException
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.accounts import LOCAL, Caller, identify

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
RETRY_AFTER_S = 1


@dataclass(frozen=True)
class BodyRule:
    """Requests with ``method`` whose path matches ``path`` (a regular expression, anchored) may
    send at most ``max_bytes`` of body, and at most ``concurrent`` of them run at once (None: no
    cap of their own)."""

    method: str
    path: str
    max_bytes: int
    concurrent: int | None = None

    def matches(self, method: str, path: str) -> bool:
        return method == self.method and re.fullmatch(self.path, path) is not None


@dataclass(frozen=True)
class GuardConfig:
    """keys: each key taken, with who sends it (``accounts.caller_keys``; none: no key, and every
    request is the local user's); public_paths: paths that need no key and are answered whatever
    the load (exact match: health); open_paths / open_prefixes: paths (exact, or starting with a
    prefix) that need no key but count against ``max_requests`` like any other (the web page)."""

    keys: tuple[tuple[bytes, Caller], ...]
    public_paths: frozenset[str]
    trusted_hosts: tuple[str, ...]
    rules: tuple[BodyRule, ...]
    default_max_bytes: int
    max_requests: int
    body_timeout_s: float
    body_min_rate: float = 16 * 1024.0
    body_grace_s: float = 10.0
    open_paths: frozenset[str] = frozenset()
    open_prefixes: tuple[str, ...] = ()

    def needs_key(self, path: str) -> bool:
        if path in self.public_paths or path in self.open_paths:
            return False
        return ".." in path or not any(path.startswith(prefix) for prefix in self.open_prefixes)


class BodyRejected(HTTPException):
    """Raised from ``receive`` when a body breaks its limit; FastAPI answers it as is."""


def _same_origin(origin: str, scheme: str, host: str) -> bool:
    """``origin`` (``scheme://host[:port]``; "null" for sandboxed frames and file:// pages) is the
    service itself, as the request's ``scheme`` and ``Host`` name it: the same scheme, host *and*
    port, so a page that another program serves on another loopback port is another origin."""
    defaults = {"http": 80, "https": 443}
    try:
        theirs, ours = urlsplit(origin), urlsplit(f"//{host}")
        their_port = theirs.port or defaults.get(theirs.scheme)
        our_port = ours.port or defaults.get(scheme)
    except ValueError:  # a port out of range or not a number
        return False
    return theirs.hostname is not None and (theirs.scheme, theirs.hostname, their_port) == (
        scheme,
        ours.hostname,
        our_port,
    )


def _reply(status: int, detail: str, retry_after: bool = False) -> JSONResponse:
    headers = {"Retry-After": str(RETRY_AFTER_S)} if retry_after else None
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)


@dataclass
class _Counters:
    in_flight: int = 0
    per_rule: dict[int, int] = field(default_factory=dict)


class RequestGuard:
    def __init__(self, app: ASGIApp, config: GuardConfig) -> None:
        self.app, self.config = app, config
        self._counters = _Counters()  # this app's requests (the event loop is single-threaded)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        method, path = scope["method"], scope["path"]
        state = scope.setdefault("state", {})
        refusal = self._refuse(method, path, headers, scope.get("scheme", "http"), state)
        if refusal is not None:
            await refusal(scope, receive, send)
            return
        counters, cfg = self._counters, self.config
        if counters.in_flight >= cfg.max_requests and path not in cfg.public_paths:  # health stays visible
            await _reply(503, "the service is busy; retry shortly", retry_after=True)(scope, receive, send)
            return
        index, rule = next(((i, r) for i, r in enumerate(cfg.rules) if r.matches(method, path)), (None, None))
        limit = rule.max_bytes if rule is not None else cfg.default_max_bytes
        length = headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > limit):
            detail = _too_large(limit, method, path) if length.isdigit() else "invalid Content-Length"
            await _reply(413 if length.isdigit() else 400, detail)(scope, receive, send)
            return
        if (
            rule is not None
            and rule.concurrent is not None
            and counters.per_rule.get(index, 0) >= rule.concurrent
        ):
            detail = f"{rule.concurrent} {method} requests like this one are in progress; retry shortly"
            await _reply(503, detail, retry_after=True)(scope, receive, send)
            return
        counters.in_flight += 1
        if index is not None:
            counters.per_rule[index] = counters.per_rule.get(index, 0) + 1
        try:
            await self._run(scope, receive, send, limit, method, path)
        finally:
            counters.in_flight -= 1
            if index is not None:
                counters.per_rule[index] -= 1

    def _refuse(
        self, method: str, path: str, headers: dict[str, str], scheme: str, state: dict
    ) -> JSONResponse | None:
        caller = LOCAL
        if self.config.keys:  # the header's own bytes (decoded as latin-1 above)
            caller = identify(headers.get("x-api-key", "").encode("latin-1"), self.config.keys)
            if caller is None and self.config.needs_key(path):
                return _reply(401, "missing or wrong API key (header X-API-Key)")
        state["caller"] = caller
        if method not in SAFE_METHODS and self._cross_site(headers, scheme):
            return _reply(403, "cross-site requests are refused (the Origin is not this service)")
        return None

    def _cross_site(self, headers: dict[str, str], scheme: str) -> bool:
        """A browser request made by another site's page (programs send neither header)."""
        if headers.get("sec-fetch-site") == "cross-site":
            return True
        origin = headers.get("origin")
        if origin is None:
            return False
        if "*" in self.config.trusted_hosts:  # keyed: another site's page cannot send the key
            return False
        return not _same_origin(origin, scheme, headers.get("host") or "")

    async def _run(
        self, scope: Scope, receive: Receive, send: Send, limit: int, method: str, path: str
    ) -> None:
        seen, done, started = 0, False, False
        cfg = self.config
        loop = asyncio.get_running_loop()
        begun = loop.time()

        async def limited() -> Message:
            nonlocal seen, done
            if done:  # the body is in; what follows is a wait for the disconnect: no timeout
                return await receive()
            # The next chunk must come within body_timeout_s, and before the average rate since
            # the first byte was asked for drops under body_min_rate (after the grace).
            behind = begun + cfg.body_grace_s + seen / cfg.body_min_rate - loop.time()
            timeout = min(cfg.body_timeout_s, behind)
            try:
                message = await asyncio.wait_for(receive(), max(timeout, 0.0))
            except TimeoutError:
                if timeout < cfg.body_timeout_s:
                    rate = f"{cfg.body_min_rate / 1024:.0f} KB/s"
                    raise BodyRejected(408, f"the request body arrived slower than {rate}") from None
                raise BodyRejected(
                    408, f"the request body stalled for more than {cfg.body_timeout_s:.0f} s"
                ) from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyRejected(413, _too_large(limit, method, path))
                done = not message.get("more_body", False)
            else:
                done = True
            return message

        async def tracked(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited, tracked)
        except BodyRejected as err:  # raised where no handler turned it into a response
            if started:
                raise
            await _reply(err.status_code, err.detail)(scope, receive, send)


def _too_large(limit: int, method: str, path: str) -> str:
    size = f"{limit / 2**20:.0f} MB" if limit >= 2**20 else f"{limit / 1024:.0f} KB"
    return f"the request body is larger than the limit of {size} for {method} {path}"
