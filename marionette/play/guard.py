"""Who may talk to the play server: its own page, and scripts on this machine. An ASGI middleware (``LocalOnly``)
in front of the app refuses, before any route runs,

- a request whose ``Host`` is not one of the loopback names with the served port (421): a page on another site that
  rebinds its DNS name to 127.0.0.1 reaches the port, but with its own name in ``Host``; a server bound to another
  interface has a token instead (``marionette play --host ... --token``), and every request must carry it (401): as
  ``?token=`` in the URL printed at start-up (the page's answer then sets it as a cookie for its later requests), as
  that cookie, or as ``Authorization: Bearer <token>`` from a script;
- a websocket, or a request other than GET and HEAD, whose ``Origin`` is not the served origin (403; a client
  that sends no ``Origin``, as scripts do, is let through): another site's page may not drive the model;
- a POST whose body is not ``application/json`` (415: a browser sends ``text/plain`` from any page without asking
  first) or whose declared length passes ``MAX_BODY`` (413, before the body is read).

A body sent without a length (chunked) is cut off by the route at ``MAX_BODY`` as it is read (``read_body``)."""

from __future__ import annotations

import hmac
import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.requests import Request

from marionette.io import loads_json
from marionette.play.access import LOOPBACK_NAMES

MAX_BODY = 64 << 10
MAX_DEPTH = 32  # JSON nesting a message may have; the page's deepest is 3

Scope = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Callable[[], Awaitable[dict]], Callable[[dict], Awaitable[None]]], Awaitable[None]]


class BodyTooLarge(ValueError):
    """A request body past ``MAX_BODY``."""


class LocalOnly:
    """The checks of the module docstring, around ``app``; ``token``: the secret of a server bound to another
    interface than loopback (None: loopback, the ``Host`` allow-list instead)."""

    def __init__(self, app: ASGIApp, token: str | None = None) -> None:
        self.app, self.token = app, token

    async def __call__(self, scope: Scope, receive, send) -> None:
        if scope["type"] in ("http", "websocket"):
            problem = refusal(scope, self.token)
            if problem is not None:
                await _refuse(scope, receive, send, *problem)
                return
            if self.token is not None and scope["type"] == "http" and _query_token(scope) is not None:
                send = _setting_cookie(send, _cookie_name(scope), self.token)
        await self.app(scope, receive, send)


def _cookie_name(scope: Scope) -> str:
    port = scope["server"][1] if scope.get("server") else 0
    return f"marionette-token-{port}"  # a cookie is per host, not per port: one per server


def _query_token(scope: Scope) -> str | None:
    for pair in scope.get("query_string", b"").decode("latin-1").split("&"):
        name, _, value = pair.partition("=")
        if name == "token":
            return value
    return None


def _tokens(scope: Scope, headers: dict[str, str]) -> list[str]:
    """The tokens a request carries: in its query, its cookie, its Authorization header."""
    out = [t for t in [_query_token(scope)] if t is not None]
    name = _cookie_name(scope)
    for part in headers.get("cookie", "").split(";"):
        key, _, value = part.strip().partition("=")
        if key == name:
            out.append(value)
    kind, _, value = headers.get("authorization", "").partition(" ")
    if kind.lower() == "bearer":
        out.append(value.strip())
    return out


def _setting_cookie(send, name: str, token: str):
    """``send`` with the token set as an HttpOnly, same-site cookie on the response it starts."""

    async def wrapped(message: dict) -> None:
        if message["type"] == "http.response.start":
            cookie = f"{name}={token}; Path=/; HttpOnly; SameSite=Strict".encode("latin-1")
            message = {**message, "headers": [*message.get("headers", []), (b"set-cookie", cookie)]}
        await send(message)

    return wrapped


def refusal(scope: Scope, token: str | None = None) -> tuple[int, str] | None:
    """(status, why) for a request ``LocalOnly`` refuses, else None."""
    headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
    port = scope["server"][1] if scope.get("server") else None
    allowed = [f"{name}:{port}" for name in LOOPBACK_NAMES]
    host = headers.get("host", "")
    if token is None and host not in allowed:
        return 421, f"host {host!r} is not this server's (it answers {' or '.join(allowed)})"
    if token is not None and not any(hmac.compare_digest(t.encode(), token.encode()) for t in _tokens(scope, headers)):
        return 401, "this server asks for its token: open the URL it printed at start-up, or send Authorization: Bearer <token>"
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
    """A message's JSON, nested at most ``MAX_DEPTH`` deep (``io.loads_json``: a ValueError naming what is wrong)."""
    return loads_json(raw, "the message", MAX_DEPTH)
