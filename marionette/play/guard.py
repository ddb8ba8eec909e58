"""Who may talk to the play server: its own page, and scripts on this machine. An ASGI middleware (``LocalOnly``)
in front of the app refuses, before any route runs,

- a request whose ``Host`` is not one of the loopback names with the served port (421): a page on another site that
  rebinds its DNS name to 127.0.0.1 reaches the port, but with its own name in ``Host``;
- a websocket, or a request other than GET and HEAD, whose ``Origin`` is not the served origin (403; a client
  that sends no ``Origin``, as scripts do, is let through): another site's page may not drive the model;
- a POST whose body is not ``application/json`` (415: a browser sends ``text/plain`` from any page without asking
  first) or whose declared length passes ``MAX_BODY`` (413, before the body is read).

A body sent without a length (chunked) is cut off by the route at ``MAX_BODY`` as it is read (``read_body``)."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.requests import Request

from marionette.io import json_depth

LOOPBACK_NAMES = ("127.0.0.1", "localhost")
MAX_BODY = 64 << 10
MAX_DEPTH = 32  # JSON nesting a message may have; the page's deepest is 3

Scope = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Callable[[], Awaitable[dict]], Callable[[dict], Awaitable[None]]], Awaitable[None]]


class BodyTooLarge(ValueError):
    """A request body past ``MAX_BODY``."""


class LocalOnly:
    """The checks of the module docstring, around ``app``."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] in ("http", "websocket"):
            problem = refusal(scope)
            if problem is not None:
                await _refuse(scope, receive, send, *problem)
                return
        await self.app(scope, receive, send)


def refusal(scope: Scope) -> tuple[int, str] | None:
    """(status, why) for a request ``LocalOnly`` refuses, else None."""
    headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
    port = scope["server"][1] if scope.get("server") else None
    allowed = [f"{name}:{port}" for name in LOOPBACK_NAMES]
    host = headers.get("host", "")
    if host not in allowed:
        return 421, f"host {host!r} is not this server's (it answers {' or '.join(allowed)})"
    method = scope.get("method", "GET")
    origin = headers.get("origin")
    if (scope["type"] == "websocket" or method not in ("GET", "HEAD")) and origin is not None and origin != f"http://{host}":
        return 403, f"a page from {origin!r} may not drive this server (its own page is http://{host}/)"
    if scope["type"] == "http" and method == "POST":
        kind = headers.get("content-type", "").split(";")[0].strip().lower()
        if kind != "application/json":
            return 415, f"a request body is application/json, not {kind or 'untyped'!r}"
        length = headers.get("content-length", "")
        if length and (not length.isdigit() or int(length) > MAX_BODY):
            return 413, f"a request body is at most {MAX_BODY} bytes, not {length}"
    return None


async def _refuse(scope: Scope, receive, send, status: int, why: str) -> None:
    if scope["type"] == "websocket":  # closed before it is accepted: the client sees an HTTP 403
        await send({"type": "websocket.close", "code": 1008, "reason": why[:120]})
        return
    body = json.dumps({"error": why}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


async def read_body(request: Request) -> bytes:
    """The request's body, read only as far as ``MAX_BODY`` (``BodyTooLarge`` past it, the rest never read)."""
    out = bytearray()
    async for chunk in request.stream():
        out += chunk
        if len(out) > MAX_BODY:
            raise BodyTooLarge(f"a request body is at most {MAX_BODY} bytes")
    return bytes(out)


def parse_message(raw: str | bytes) -> Any:
    """A message's JSON, nested at most ``MAX_DEPTH`` deep (a ValueError naming what is wrong otherwise)."""
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else raw
    except UnicodeDecodeError as err:
        raise ValueError(f"the body is not JSON: {err}") from None
    if json_depth(text) > MAX_DEPTH:
        raise ValueError(f"a message is nested at most {MAX_DEPTH} levels deep")
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"the body is not JSON: {err}") from None
