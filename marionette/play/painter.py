"""Painting a live session: the small observation model relays over the session's pose frames in its own thread.

The session starts a scene with the recorded RGB frame at the seed's last row (``recorded_frame``) and, so that the
first pose frame shows what that RGB frame shows, a follow camera seeded at the recorded camera of that row. From
then on every played frame's G-buffer codes are fed in (reduced to the model's size as training reduces them:
``observation.data.pose_frames``), and whenever a chunk's worth (the model's T − 1 frames after the last painted one)
is there, ``observation.relay.Relay`` paints it from the last painted frame — the relay ``marionette generate``
runs, at whatever rate the machine manages. The rate and how far painting is behind are reported with every
painted frame. Painting never holds the live loop: its thread runs at a lower priority (``PAINT_NICE``), and
when it is more than ``MAX_BEHIND_CHUNKS`` chunks behind, it
skips to the newest whole chunk (and says how many frames it skipped), keeping its last painted frame as the next
chunk's first.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from marionette.bridge.gbuffer import to_codes
from marionette.chunks import relay_step
from marionette.corpus import Corpus, video_shards
from marionette.observation.data import check_size, pose_frames, rgb_frames
from marionette.observation.relay import Relay
from marionette.video import decode_frames

MAX_BEHIND_CHUNKS = 2
PAINT_NICE = 10  # the painting thread's niceness (Linux: per thread)


def recorded_frame(corpus: Corpus, segment: str, frame: int) -> np.ndarray:
    """The recorded RGB frame (H, W, 3) uint8 of ``segment`` at source frame ``frame``, from a video chunk holding it."""
    row = corpus.segment_row(segment)
    path = corpus.video_path(row["shard"])
    chunks = video_shards.read_chunks(path, segment, kinds=(video_shards.CHUNK_KIND, video_shards.RGB_KIND))
    for key, m in sorted(chunks.items()):
        rec = video_shards.chunk_record(m["json"], key, str(path))
        lo, hi = (int(x) for x in rec["frames"])
        if lo <= frame < hi and video_shards.RGB_KIND in m:
            got = decode_frames(m[video_shards.RGB_KIND], {frame - lo}).get(frame - lo)
            if got is not None:
                return got
    raise ValueError(f"{path}: no video chunk of segment {segment!r} holds source frame {frame}")


class Painter:
    """The painting thread of a live session (module doc); ``publish(meta, rgb)`` gets each painted frame."""

    def __init__(self, model_dir: Path, view_size: tuple[int, int], steps: int = 4, seed: int = 0, log=print) -> None:
        from marionette.observation.generate import wan_directory
        from marionette.observation.train import load_model

        if wan_directory(Path(model_dir)):
            raise ValueError(
                f"{model_dir}: a Wan2.2-Fun-Control directory; live painting runs the small observation model "
                "(`marionette generate` paints a recorded session with Wan)"
            )
        self.model = load_model(model_dir)
        c = self.model.config
        if c.control != "pose":
            raise ValueError(f"{model_dir}: a model controlled by {c.control!r} cannot paint a pose video")
        self.size = c.size
        self.factor = check_size(tuple(view_size), c.size, f"the play view ({view_size[0]}x{view_size[1]}, --size)")
        self.T, self.steps, self.seed, self.log = c.frames, int(steps), int(seed), log
        self.publish: Callable[[dict, np.ndarray], None] = lambda meta, rgb: None
        self._cond = threading.Condition()
        self._pose: dict[int, torch.Tensor] = {}
        self._scene = 0
        self._start: tuple | None = None
        self._stop = False
        self.painted_fps: float | None = None
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name="marionette-paint", daemon=True)
        self._thread.start()

    def start_scene(self, first_rgb: np.ndarray, first_codes: np.ndarray) -> None:
        """A new scene: its first RGB frame (H·f, W·f, 3) uint8 at any whole multiple of the model's size and the
        G-buffer codes (view size) of frame 0."""
        f = check_size(first_rgb.shape[:2], self.size, "the recorded first frame")
        with self._cond:
            self._scene += 1
            self._start = (self._scene, rgb_frames(first_rgb[None], f)[0], pose_frames(first_codes[None], self.factor)[0])
            self._pose = {0: self._start[2]}
            self._cond.notify_all()

    def feed(self, frame: int, rgb_float: np.ndarray) -> None:
        """Played frame ``frame``'s rendered G-buffer floats (view size)."""
        pose = pose_frames(to_codes(rgb_float)[None], self.factor)[0]
        with self._cond:
            self._pose[frame] = pose
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout=60)

    def _run(self) -> None:
        with contextlib.suppress(OSError, AttributeError):  # the live view comes first: this thread (and the torch
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), PAINT_NICE)  # threads it starts) yields to it
        try:
            self._paint()
        except Exception as err:  # noqa: BLE001 - shown in the session's status; the live view goes on
            self.error = f"{type(err).__name__}: {err}"
            self.log(f"play: painting stopped: {self.error}")

    def _paint(self) -> None:
        scene, relay, at, skipped = 0, None, 0, 0
        step = relay_step(self.T)
        while True:
            with self._cond:
                while (
                    not self._stop and not (self._start and self._start[0] != scene) and not (relay and at + step in self._pose)
                ):
                    self._cond.wait(timeout=0.5)
                if self._stop:
                    return
                if self._start and self._start[0] != scene:
                    scene, first, pose0 = self._start
                    relay, at, skipped = Relay(self.model, first, pose0, self.steps, self.seed), 0, 0
                    self._emit(0, first, scene, at, 0)
                    continue
                newest = max(self._pose)
                if newest - at > MAX_BEHIND_CHUNKS * step:  # far behind: jump to the newest whole chunk
                    jump = at + ((newest - at) // step - 1) * step
                    skipped += jump - at
                    relay.painted += jump - at
                    self._pose[jump] = self._pose[at]  # the chunk starts from the last painted frame
                    at = jump
                control = torch.stack([self._pose[k] for k in range(at, at + step + 1)])
                for k in [k for k in self._pose if k < at + step]:
                    del self._pose[k]
            t0 = time.perf_counter()
            with torch.no_grad():
                frames = relay.paint(control)
            took = time.perf_counter() - t0
            self.painted_fps = round(step / took, 2)
            with self._cond:
                behind = max(0, max(self._pose, default=at + step) - (at + step))
            for k, rgb in enumerate(frames, start=1):
                self._emit(at + k, rgb, scene, behind, skipped)
            at += step

    def _emit(self, frame: int, rgb: torch.Tensor, scene: int, behind: int, skipped: int) -> None:
        img = ((rgb.permute(1, 2, 0).numpy() + 1.0) * 127.5).round().clip(0, 255).astype(np.uint8)
        meta = {
            "type": "painted",
            "frame": frame,
            "scene": scene,
            "painted_fps": self.painted_fps,
            "behind": behind,
            "skipped": skipped,
            "width": int(img.shape[1]),
            "height": int(img.shape[0]),
        }
        self.publish(meta, img)
