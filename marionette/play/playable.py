"""What the page drives, live (``session.LiveSession``) or replayed (``replay.ReplaySession``): frames one at a time,
pause and single steps, the camera, the stage map, and one dispatcher for the page's messages."""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from marionette.corpus import MODEL_FPS

from .messages import int_field
from .view import FrameView, Orbit


class Playable(ABC):
    """What the page drives, live or replayed: frames one at a time (``advance``), pause and single steps, the camera,
    the stage map, and one dispatcher for the page's messages (``handle``)."""

    kind = ""
    fps = MODEL_FPS

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.paused = False
        self._steps = 0
        self.camera_mode, self.orbit = "follow", Orbit()
        self.view: FrameView | None = None
        self._last: dict | None = None
        self._pixels: np.ndarray | None = None
        self._map: dict = {}

    @abstractmethod
    def advance(self) -> tuple[dict, np.ndarray] | None:
        """The next frame (meta, pixels), or None when none is due."""

    @abstractmethod
    def status(self) -> dict:
        """What the page and ``GET /api/status`` show."""

    def _may_step(self) -> bool:
        """Whether a frame is due: playing, or a single step queued (which it takes)."""
        if not self.paused:
            return True
        if self._steps > 0:
            self._steps -= 1
            return True
        return False

    def pause(self, paused: bool) -> dict:
        if not isinstance(paused, bool):
            raise ValueError(f"paused is true or false, not {paused!r}")
        with self.lock:
            self.paused = paused
        return {"paused": paused}

    def single_step(self, frames: int = 1) -> dict:
        """Advance ``frames`` frames while paused."""
        n = int_field({"frames": frames}, "frames", 1, 1000)
        with self.lock:
            self._steps += n
        return {"paused": self.paused, "queued": self._steps}

    def current(self) -> tuple[dict, np.ndarray] | None:
        """The newest frame (meta, pixels), e.g. for a page that connects while paused; None before the first."""
        with self.lock:
            return None if self._last is None else (self._last, self._pixels)

    def set_camera(self, msg: dict) -> dict:
        """{"mode": "follow" | "orbit"[, "yaw", "pitch", "distance"]}."""
        mode = msg.get("mode", self.camera_mode)
        if mode not in ("follow", "orbit"):
            raise ValueError(f"camera mode {mode!r} is not 'follow' or 'orbit'")
        vals = {k: msg.get(k, getattr(self.orbit, k)) for k in ("yaw", "pitch", "distance")}
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in vals.values()):
            raise ValueError(f"camera: yaw, pitch and distance are numbers, not {vals}")
        with self.lock:
            self.orbit, self.camera_mode = Orbit(**vals).checked(), mode
            return {"mode": mode, **vars(self.orbit)}

    def stage_map(self) -> dict:
        return self._map

    def close(self) -> None:
        with self.lock:
            if self.view is not None:
                self.view.release()
                self.view = None

    HANDLERS = ("pause", "step", "camera")

    def handle(self, msg: Any) -> dict:
        """One message of the page's websocket ({"type": ..., ...}); a bad one is a ValueError naming what is wrong."""
        if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
            raise ValueError('a message is a JSON object with a "type"')
        kind = msg["type"]
        if kind not in self.HANDLERS:
            raise ValueError(f"unknown message type {kind!r}; a {self.kind} session takes {list(self.HANDLERS)}")
        body = {k: v for k, v in msg.items() if k not in ("type", "seq")}
        return getattr(self, f"_on_{kind}")(body)

    def _on_pause(self, m: dict) -> dict:
        return self.pause(m.get("paused", not self.paused))

    def _on_step(self, m: dict) -> dict:
        return self.single_step(m.get("frames", 1))

    def _on_camera(self, m: dict) -> dict:
        return self.set_camera(m)
