"""The play page's server: a Starlette app on uvicorn, bound to 127.0.0.1 (another interface only with a token), with
a websocket for frames and control.

One thread (``Player``) owns the session and its GL context: it calls ``session.advance()`` at the session's
frame rate (``fps`` 0: as fast as it can) and hands each frame to every connected page. A page that cannot keep
up loses frames, never the server: each client's ``Outbox`` keeps the newest ``QUEUE_FRAMES`` live frames (and up
to ``QUEUE_PAINTED`` painted ones, which come a chunk at a time). A frame goes out as two websocket messages: its
meta as JSON text ({"type": "frame", ...}, with the frame rate and the control-to-frame latency the server
measured), then its pixels as bytes (H × W × 3, row-major RGB): the G-buffer (height, render id, inverse depth) of
a live frame, the RGB of a painted one ({"type": "painted", ...}, when the session paints).

The page sends controls on the same websocket ({"type": ..., "seq": n, ...}, ``Playable.handle``) and gets a
{"type": "reply"} or {"type": "error", "message"} back with the same ``seq``. Scripts use the HTTP API:
``GET /api/status``, ``GET /api/actions``, ``GET /api/map``, ``GET /api/segments`` and ``POST /api/<type>`` with the
message as a JSON body (``control``, ``reset``, ``record``, ``rules``, ``pause``, ``step``, ``camera``, ``bind``,
``drive``, ``seek``); a bad request is a 400 whose JSON ``error`` names what was wrong, an unknown type a 404, a
recording name already taken a 409. Only the page's own origin and scripts on this machine get that far
(``guard.LocalOnly``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading
import time
from collections import deque
from importlib import resources
from typing import Any

import numpy as np
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from .access import LOOPBACK_NAMES
from .guard import BodyTooLarge, LocalOnly, parse_message, read_body
from .playable import Playable

QUEUE_FRAMES = 1
QUICK = {"control", "move"}  # handled on the event loop itself: they only take the controls' lock, briefly
QUEUE_PAINTED = 256
HOST = "127.0.0.1"  # never another interface: the page drives a model on this machine


def percentile(xs, q: float) -> float | None:
    return round(float(np.percentile(np.asarray(xs), q)), 2) if len(xs) else None


class Player:
    """The thread that steps the session and fans its frames out to the connected pages."""

    def __init__(self, session: Playable, fps: float | None = None, log=print) -> None:
        self.session = session
        self.fps = float(session.fps if fps is None else fps)
        self.log = log
        self.clients: set[Outbox] = set()
        self.loop: asyncio.AbstractEventLoop | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.sent = deque(maxlen=60)  # publish times of the last frames
        self.latency_ms = deque(maxlen=200)  # control received → first frame that answers it
        self._asked: dict[int, float] = {}
        self.error: str | None = None

    # -- the thread --------------------------------------------------------------------------------

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        if getattr(self.session, "painter", None) is not None:
            self.session.painter.publish = self.publish_painted
        self._thread = threading.Thread(target=self._run, name="marionette-play", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def _run(self) -> None:
        period = 1.0 / self.fps if self.fps > 0 else 0.0
        due = time.perf_counter()
        try:
            while not self._stop.is_set():
                try:
                    out = self.session.advance()
                except Exception as err:  # noqa: BLE001 - shown on the page; the session pauses, the server stays up
                    self.error = f"{type(err).__name__}: {err}"
                    self.log(f"play: frame failed: {self.error}")
                    self.session.pause(True)
                    out = None
                now = time.perf_counter()
                if out is None:
                    time.sleep(0.01)
                    due = time.perf_counter()
                    continue
                self._publish(*out, now)
                due = max(due + period, now - period)  # late by more than a frame: do not burst to catch up
                time.sleep(max(0.0, due - time.perf_counter()))
        finally:
            self.session.close()

    def _publish(self, meta: dict, pixels: np.ndarray, now: float) -> None:
        self.sent.append(now)
        ack = meta.get("ack")
        if ack is not None:
            for seq in [s for s in self._asked if s <= ack]:
                self.latency_ms.append(1e3 * (now - self._asked.pop(seq)))
        meta = {**meta, "fps": self.measured_fps(), "latency_ms": self.latency()}
        item = (json.dumps(meta), np.ascontiguousarray(pixels).tobytes())
        self._fan_out(item, False)

    def publish_painted(self, meta: dict, rgb: np.ndarray) -> None:
        """A painted frame (from the painting thread) to every page."""
        self._fan_out((json.dumps(meta), np.ascontiguousarray(rgb).tobytes()), True)

    def _fan_out(self, item: tuple[str, bytes], painted: bool) -> None:
        if self.loop is not None:
            for box in list(self.clients):
                self.loop.call_soon_threadsafe(box.offer, item, painted)

    def asked(self, reply: dict) -> None:
        """Note when a control arrived, to time the frame that answers it."""
        if isinstance(reply, dict) and isinstance(reply.get("seq"), int):
            self._asked[reply["seq"]] = time.perf_counter()
            if len(self._asked) > 1000:
                self._asked.pop(min(self._asked))

    def measured_fps(self) -> float | None:
        s = self.sent
        if len(s) < 2 or s[-1] - s[0] <= 0 or time.perf_counter() - s[-1] > 1.0:
            return None
        return round((len(s) - 1) / (s[-1] - s[0]), 2)

    def latency(self) -> dict:
        return {"p50": percentile(self.latency_ms, 50), "p95": percentile(self.latency_ms, 95), "n": len(self.latency_ms)}


class Outbox:
    """One page's queue of (text, bytes) messages: the newest ``QUEUE_FRAMES`` live frames and ``QUEUE_PAINTED``
    painted ones (a page that is behind gets the newest)."""

    def __init__(self) -> None:
        self.items: deque = deque()
        self.ready = asyncio.Event()

    def offer(self, item: tuple[str, bytes], painted: bool = False) -> None:
        self.items.append((painted, item))
        cap = QUEUE_PAINTED if painted else QUEUE_FRAMES
        kept = [i for i, (p, _) in enumerate(self.items) if p == painted]
        for i in reversed(kept[: max(0, len(kept) - cap)]):
            del self.items[i]
        self.ready.set()

    async def get(self) -> tuple[str, bytes]:
        while not self.items:
            self.ready.clear()
            await self.ready.wait()
        return self.items.popleft()[1]


async def handled(session: Playable, msg: Any) -> dict:
    """``session.handle(msg)``: a control at once (the key's latency is the product), anything else in a worker
    thread (a reset or a rule waits for the frame being made)."""
    if isinstance(msg, dict) and msg.get("type") in QUICK:
        return session.handle(msg)
    return await asyncio.get_running_loop().run_in_executor(None, session.handle, msg)


def _page() -> str:
    return resources.files("marionette.play").joinpath("page.html").read_text(encoding="utf-8")


def create_app(session: Playable, fps: float | None = None, log=print, token: str | None = None) -> Starlette:
    """The play app over ``session``; its ``Player`` starts with the app and stops (closing the session) with it.
    ``token``: the secret every request must carry (``guard.LocalOnly``; None on loopback)."""
    player = Player(session, fps, log)

    @contextlib.asynccontextmanager
    async def lifespan(app):
        player.start(asyncio.get_running_loop())
        try:
            yield
        finally:
            await asyncio.get_running_loop().run_in_executor(None, player.stop)

    async def page(request: Request) -> HTMLResponse:
        return HTMLResponse(_page())

    def status() -> dict:
        return {**session.status(), "measured_fps": player.measured_fps(), "latency_ms": player.latency(), "error": player.error}

    async def api_status(request: Request) -> JSONResponse:
        return JSONResponse(status())

    async def api_actions(request: Request) -> JSONResponse:
        if session.kind != "live":
            return JSONResponse({"entities": {}, "bindings": {}, "driven": None})
        with session.lock:
            return JSONResponse(
                {
                    "entities": {e: [a.to_json() for a in acts] for e, acts in session.actions.items()},
                    "bindings": {e: dict(b) for e, b in session.bindings.items()},
                    "driven": session.driven,
                }
            )

    async def api_map(request: Request) -> JSONResponse:
        return JSONResponse(session.stage_map())

    async def api_segments(request: Request) -> JSONResponse:
        return JSONResponse({"segments": session.segments() if session.kind == "live" else [session.segment]})

    async def api_post(request: Request) -> JSONResponse:
        kind = request.path_params["kind"]
        if kind not in session.HANDLERS:
            return JSONResponse(
                {"error": f"no such action {kind!r}; this {session.kind} session takes {list(session.HANDLERS)}"}, 404
            )
        try:
            body = parse_message(await read_body(request) or b"{}")
        except BodyTooLarge as err:
            return JSONResponse({"error": str(err)}, 413)
        except ValueError as err:
            return JSONResponse({"error": str(err)}, 400)
        if not isinstance(body, dict):
            return JSONResponse({"error": f"the body is a JSON object, not {type(body).__name__}"}, 400)
        try:
            reply = await handled(session, {**body, "type": kind})
        except FileExistsError as err:
            return JSONResponse({"error": str(err)}, 409)
        except ValueError as err:
            return JSONResponse({"error": str(err)}, 400)
        player.asked(reply)
        return JSONResponse(reply)

    async def ws(websocket: WebSocket) -> None:
        await websocket.accept()
        box = Outbox()
        first = session.current()
        if first is not None:
            box.offer(
                (json.dumps({**first[0], "fps": player.measured_fps(), "latency_ms": player.latency()}), first[1].tobytes())
            )
        player.clients.add(box)

        async def send() -> None:
            while True:
                text, data = await box.get()
                await websocket.send_text(text)
                await websocket.send_bytes(data)

        async def receive() -> None:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    raise WebSocketDisconnect(message.get("code", 1000))
                seq = None
                try:
                    if message.get("text") is None:
                        raise ValueError("a message is JSON text, not binary")
                    msg = parse_message(message["text"])
                    seq = msg.get("seq") if isinstance(msg, dict) else None
                    reply = await handled(session, msg)
                    player.asked(reply)
                    await websocket.send_text(json.dumps({"type": "reply", "seq": seq, "result": reply}))
                except (ValueError, FileExistsError) as err:
                    await websocket.send_text(json.dumps({"type": "error", "seq": seq, "message": str(err)}))

        tasks = [asyncio.create_task(send()), asyncio.create_task(receive())]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            player.clients.discard(box)
            for t in tasks:
                t.cancel()
            for t in tasks:  # a client gone mid-stream ends its own tasks only
                with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError, OSError):
                    await t

    routes = [
        Route("/", page),
        Route("/api/status", api_status),
        Route("/api/actions", api_actions),
        Route("/api/map", api_map),
        Route("/api/segments", api_segments),
        Route("/api/{kind}", api_post, methods=["POST"]),
        WebSocketRoute("/ws", ws),
    ]
    app = Starlette(routes=routes, lifespan=lifespan, middleware=[Middleware(LocalOnly, token=token)])
    app.state.player = player
    return app


class Server:
    """The app on uvicorn at ``host``:``port`` (0: a free port) in a background thread: ``start``, ``wait``, ``stop``.
    ``host`` is 127.0.0.1 unless ``token`` is given (``play.access``): then every request must carry it."""

    def __init__(
        self, session: Playable, port: int = 8765, fps: float | None = None, log=print, host: str = HOST, token: str | None = None
    ) -> None:
        import uvicorn

        if token is None and host not in LOOPBACK_NAMES:
            raise ValueError(f"the play server binds {host} only with a token")
        self.host, self.token = host, token
        self.app = create_app(session, fps, log, token)
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host=host, port=int(port), log_level="warning", ws="websockets-sansio", lifespan="on")
        )
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self.server.servers[0].sockets[0].getsockname()[1])

    @property
    def url(self) -> str:
        """The page's address: on this machine, with the token in it where the server has one."""
        return f"http://{HOST}:{self.port}/" + (f"?token={self.token}" if self.token is not None else "")

    @property
    def urls(self) -> list[str]:
        """The page's addresses to print: ``url``, and where the server binds another interface, that one's."""
        if self.host in LOOPBACK_NAMES:
            return [self.url]
        shown = socket.gethostname() if self.host in ("0.0.0.0", "::") else self.host
        return [f"http://{shown}:{self.port}/?token={self.token}", self.url]

    def wait(self) -> None:
        """Block until the server stops (Ctrl-C in this thread stops it: ``serve``)."""
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout=0.5)

    def start(self, timeout: float = 60.0) -> Server:
        self._thread = threading.Thread(target=self.server.run, name="marionette-play-server", daemon=True)
        self._thread.start()
        t0 = time.monotonic()
        while not self.server.started:
            if not self._thread.is_alive() or time.monotonic() - t0 > timeout:
                raise RuntimeError(f"the play server did not start on {self.host} within {timeout:g} s")
            time.sleep(0.05)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=60)
