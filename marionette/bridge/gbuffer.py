"""The pose-control G-buffer: its channel encoding and its lossless 10-bit video file.

Channels (floats in [0, 1] as rendered, then 10-bit codes c = round(1023 · v)):

- R, height: ĥ = (y − h_min) / (h_max − h_min) clipped to [0, 1], with y the world height of the
  surface point; R = 0.5 + 0.5 ĥ on terrain, 0.2 ĥ on a bone.
- G, identity: id / 255 — 0 terrain, a rig's ``id_band`` for its bones (weapon 60–99, monster
  105–194, hunter 195–254), ids in breadth-first order of the rig's child joints.
- B, inverse depth: 1 − (z − z_near) / (z_far − z_near), z the view depth (metres along the optical
  axis), clipped to [0, 1].
- Background: (0, 0, 0) — no surface. A covered pixel always has G > 0 (a bone) or R ≥ 0.5 (terrain).

File: Matroska, one FFV1 stream (level 3, intra only) in ``gbrp10le`` — planar RGB, 10 bits per channel,
no chroma subsampling, lossless — with the container tag ``MARIONETTE_GBUFFER`` holding the JSON
{"version", "h_min", "h_max", "z_near", "z_far", "width", "height", "fps"}: decoding needs nothing else.

Quantisation bounds after decoding (the render target is half float: up to one ulp, 2⁻¹¹ in [0.5, 1),
since llvmpipe truncates, before the 10-bit rounding of ±1/2046): height ±(h_max − h_min)·2·(1/2046 + 2⁻¹¹)
on terrain and ±(h_max − h_min)·5·(1/2046 + 2⁻¹¹) on bones (``height_bound``); inverse depth
±(1/2046 + 2⁻¹¹), i.e. depth ±(z_far − z_near)(1/2046 + 2⁻¹¹) (``depth_bound``); ids exact.
"""

from __future__ import annotations

import io
import json
import queue
import threading
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np

from marionette.io import atomic_path, regular_file

GBUFFER_VERSION = 1
TAG = "MARIONETTE_GBUFFER"
CODE_MAX = 1023
HALF_ERR = 2.0**-11  # one ulp of a half float in [0.5, 1): drivers may truncate rather than round
BACKGROUND_ID = -1


@dataclass(frozen=True)
class GBufferMeta:
    """What decoding a G-buffer file needs: the height range (m), the depth range (m), size and rate."""

    h_min: float
    h_max: float
    z_near: float
    z_far: float
    width: int
    height: int
    fps: float
    version: int = GBUFFER_VERSION

    def height_bound(self, terrain: bool = True) -> float:
        """Largest decoding error (m) of a height on terrain (or on a bone)."""
        step = (self.h_max - self.h_min) * 2 * (1 / (2 * CODE_MAX) + HALF_ERR)
        return step if terrain else 2.5 * step

    def depth_bound(self) -> float:
        """Largest decoding error (m) of a depth."""
        return (self.z_far - self.z_near) * (1 / (2 * CODE_MAX) + HALF_ERR)


@dataclass
class GBufferFrame:
    """One decoded frame: height (H, W) metres (NaN on background), id (H, W) int16 (−1 background,
    0 terrain, else a bone's id), inv_depth (H, W) in [0, 1] (0 background) and depth (H, W) metres (NaN background)."""

    height: np.ndarray
    id: np.ndarray
    inv_depth: np.ndarray
    depth: np.ndarray


def to_codes(rgb: np.ndarray) -> np.ndarray:
    """Rendered floats (H, W, 3) → 10-bit codes (H, W, 3) uint16."""
    v = np.clip(np.nan_to_num(np.asarray(rgb, np.float32)), 0.0, 1.0)
    return np.rint(v * CODE_MAX).astype(np.uint16)


# the code of every half-float bit pattern: ``HALF_TO_CODE[bits]`` equals ``to_codes`` of that half's value
HALF_TO_CODE = to_codes(np.arange(1 << 16, dtype=np.uint16).view(np.float16).astype(np.float32))


def decode_codes(codes: np.ndarray, meta: GBufferMeta) -> GBufferFrame:
    """10-bit codes (H, W, 3) → the frame's height, id and depth (module docstring)."""
    c = np.asarray(codes).astype(np.float64) / CODE_MAX
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    ids = np.rint(g * 255).astype(np.int16)
    covered = (codes[..., 0] > 0) | (codes[..., 1] > 0) | (codes[..., 2] > 0)
    ids[~covered] = BACKGROUND_ID
    terrain = covered & (ids == 0)
    h_hat = np.where(terrain, (r - 0.5) / 0.5, r / 0.2)
    height = np.where(covered, meta.h_min + h_hat * (meta.h_max - meta.h_min), np.nan)
    inv = np.where(covered, b, 0.0)
    depth = np.where(covered, meta.z_near + (1 - b) * (meta.z_far - meta.z_near), np.nan)
    return GBufferFrame(height, ids, inv, depth)


def _planar_frame(frame: np.ndarray, width: int, height: int, where: str) -> av.VideoFrame:
    """A gbrp10le frame from codes: (H, W, 3) uint16 [R, G, B] interleaved, or (3, H, W) uint16 planes [G, B, R]."""
    if frame.dtype != np.uint16:
        frame = to_codes(frame)
    if frame.shape == (height, width, 3):
        planes = (frame[..., 1], frame[..., 2], frame[..., 0])
    elif frame.shape == (3, height, width):
        planes = tuple(frame)
    else:
        raise ValueError(f"{where}: frame is {frame.shape}, expected {(height, width, 3)} or {(3, height, width)}")
    vf = av.VideoFrame(width, height, "gbrp10le")
    for plane, data in zip(vf.planes, planes):  # gbrp: planes G, B, R
        dst = np.frombuffer(plane, np.uint16).reshape(height, plane.line_size // 2)
        dst[:, :width] = data
    return vf


# Below this many pixels a frame, handing each frame to the encoder thread costs more than the overlap saves: at
# 36 × 64 the two threads trade the GIL on every frame and the pass takes 2.5× the serial loop's time; from 72 × 128
# up they are even or the overlap wins (docs/tradeoffs.md, "The bridge: the encoder on a thread of its own").
OVERLAP_MIN_PIXELS = 72 * 128


def write_gbuffer(path: Path, frames: Iterable[np.ndarray], meta: GBufferMeta, overlap: bool | None = None) -> int:
    """Encode frames losslessly to ``path`` (atomic); returns the frame count. A frame is rendered floats
    (H, W, 3), 10-bit codes (H, W, 3) uint16, or code planes (3, H, W) uint16 in G, B, R order
    (``Rasterizer.render_planes``, the fast path).

    With ``overlap`` the encoder runs on a thread of its own, fed through a short queue, while this thread
    produces the frames (the renderer's GL context stays on the thread that made it): FFV1 and the GL
    readback both release the GIL, so a render + encode pass takes about the slower of the two instead of
    their sum. One encoder consumes the frames in order, so the bytes are those of the serial loop. The default
    (None) overlaps frames of at least ``OVERLAP_MIN_PIXELS`` pixels and encodes smaller ones on this thread."""
    path = Path(path)
    if overlap is None:
        overlap = meta.width * meta.height >= OVERLAP_MIN_PIXELS
    # bitexact: no random segment UID or encoder string, so a re-render is byte-identical
    with atomic_path(path) as tmp, av.open(str(tmp), "w", format="matroska", options={"fflags": "+bitexact"}) as c:
        c.metadata[TAG] = json.dumps(asdict(meta), sort_keys=True)
        rate = Fraction(meta.fps).limit_denominator(1001)
        s = c.add_stream("ffv1", rate=rate)
        s.width, s.height, s.pix_fmt = meta.width, meta.height, "gbrp10le"
        s.options = {"level": "3", "g": "1", "slicecrc": "1"}
        s.thread_count = 1

        def encode(f: np.ndarray | None, n: int) -> None:
            frame = None if f is None else _planar_frame(f, meta.width, meta.height, f"{path}: frame {n}")
            for p in s.encode(frame):
                c.mux(p)

        n = _encode_overlapped(frames, encode) if overlap else _encode_serially(frames, encode)
    return n


def _encode_serially(frames: Iterable[np.ndarray], encode) -> int:
    n = 0
    for f in frames:
        encode(f, n)
        n += 1
    encode(None, n)  # flush
    return n


QUEUED_FRAMES = 4  # frames in flight between the producer and the encoder thread


def _encode_overlapped(frames: Iterable[np.ndarray], encode) -> int:
    """``_encode_serially`` with ``encode`` on a thread of its own; an error on either side stops both and is
    raised here (the producer's first)."""

    q: queue.Queue = queue.Queue(maxsize=QUEUED_FRAMES)
    failed: list[BaseException] = []
    done = object()

    def consume() -> None:
        n = 0
        try:
            while (f := q.get()) is not done:
                if not failed:
                    encode(f, n)
                n += 1
            if not failed:
                encode(None, n)
        except BaseException as exc:  # noqa: BLE001 (handed to the producer, which raises it)
            failed.append(exc)
            while q.get() is not done:  # drain, so the producer never blocks on a full queue
                pass

    worker = threading.Thread(target=consume, name="gbuffer-encode", daemon=True)
    worker.start()
    n = 0
    try:
        for f in frames:
            if failed:
                break
            q.put(f)
            n += 1
    finally:
        q.put(done)
        worker.join()
    if failed:
        raise failed[0]
    return n


def _source(data: Path | bytes, name: str | None) -> tuple[Any, Any]:
    """What ``av.open`` reads (a path, or a file's bytes, e.g. a webdataset member) and what errors call it."""
    if isinstance(data, bytes | bytearray):
        return io.BytesIO(data), name or "<bytes>"
    regular_file(Path(data))  # a FIFO would block the decoder
    return str(data), name or data


def read_gbuffer_meta(path: Path | bytes, name: str | None = None) -> GBufferMeta:
    """The metadata of a G-buffer file (a path, or its bytes, called ``name`` in errors); a clear error if it is not one."""
    src, where = _source(path, name)
    try:
        with av.open(src) as c:
            raw = c.metadata.get(TAG)
    except (av.error.FFmpegError, OSError) as err:
        raise ValueError(f"{where}: cannot open as a G-buffer video: {err}") from err
    if raw is None:
        raise ValueError(f"{where}: no {TAG} metadata: not a Marionette G-buffer video")
    d = json.loads(raw)
    if d.get("version") != GBUFFER_VERSION:
        raise ValueError(f"{where}: G-buffer version {d.get('version')!r}, this reader knows {GBUFFER_VERSION}")
    return GBufferMeta(**d)


def iter_codes(path: Path | bytes, name: str | None = None) -> Iterator[np.ndarray]:
    """The raw 10-bit codes (H, W, 3) uint16 of each frame of a G-buffer file (a path or its bytes)."""
    src, where = _source(path, name)
    with av.open(src) as c:
        s = c.streams.video[0]
        if s.codec_context.pix_fmt != "gbrp10le":
            raise ValueError(f"{where}: pixel format {s.codec_context.pix_fmt}, a G-buffer is gbrp10le")
        for frame in c.decode(s):
            yield frame.to_ndarray(format="gbrp10le")


def decode_gbuffer(path: Path) -> tuple[list[GBufferFrame], GBufferMeta]:
    """Decode a G-buffer video: per frame height, id, inv_depth (and depth), and its metadata."""
    meta = read_gbuffer_meta(path)
    return [decode_codes(c, meta) for c in iter_codes(path)], meta
