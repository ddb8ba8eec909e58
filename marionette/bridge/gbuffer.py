"""The pose-control G-buffer: its channel encoding and its two lossless 10-bit file encodings.

Channels (floats in [0, 1] as the fragment shader computes them, stored as 10-bit codes c = round(1023 · v)):

- R, height: ĥ = (y − h_min) / (h_max − h_min) clipped to [0, 1], with y the world height of the
  surface point; R = 0.5 + 0.5 ĥ on terrain, 0.2 ĥ on a bone.
- G, identity: id / 255 — 0 terrain, a rig's ``id_band`` for its bones (weapon 60–99, monster
  105–194, hunter 195–254), ids in breadth-first order of the rig's child joints.
- B, inverse depth: 1 − (z − z_near) / (z_far − z_near), z the view depth (metres along the optical
  axis), clipped to [0, 1].
- Background: (0, 0, 0) — no surface. A covered pixel always has G > 0 (a bone) or R ≥ 0.5 (terrain).

Files, the same codes and metadata in either (``write_gbuffer`` picks by the name's suffix; every reader
takes both, told apart by their first bytes):

- ``.gbz``, the corpus's pose targets: ``GBZ_MAGIC``; the metadata JSON (a little-endian u32 length, then
  the JSON); per frame a u32 length and one zstd frame (level ``GBZ_LEVEL``) of its pixels' packed codes, one
  little-endian u32 a pixel, rows top-down: G | B << 10 | R << 20 (``pack_planes``, what the renderer writes);
  then ``GBZ_END`` (u32) and the frame count (u32). Encoding a 704 × 1280 frame costs a few times less than
  FFV1 for about as many bytes, decoding several times less (docs/tradeoffs.md, "The G-buffer codec");
  rewriting the same frames gives the same bytes.
- ``.mkv``, a video any player opens (``marionette render``, rollouts, play recordings): Matroska, one FFV1
  stream (level 3, intra only) in ``gbrp10le`` — planar RGB, 10 bits per channel, no chroma subsampling —
  with the container tag ``MARIONETTE_GBUFFER`` holding the metadata JSON.

The metadata JSON is {"version", "h_min", "h_max", "z_near", "z_far", "width", "height", "fps"}: decoding
needs nothing else.

Quantisation bounds after decoding (the 10-bit rounding, ±1/2046, plus ``SHADER_ERR`` for the shader's float32
arithmetic): height ±(h_max − h_min)·2·(1/2046 + ``SHADER_ERR``) on terrain and ±(h_max − h_min)·5·(1/2046 +
``SHADER_ERR``) on bones (``height_bound``); inverse depth ±(1/2046 + ``SHADER_ERR``), i.e. depth
±(z_far − z_near)(1/2046 + ``SHADER_ERR``) (``depth_bound``); ids exact.
"""

from __future__ import annotations

import dataclasses
import io
import json
import queue
import struct
import threading
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path
from typing import BinaryIO

import av
import numpy as np
import pyarrow as pa

from marionette.io import atomic_path, loads_json, regular_file

GBUFFER_VERSION = 1
TAG = "MARIONETTE_GBUFFER"
CODE_MAX = 1023
SHADER_ERR = 2.0**-16  # the shader's float32 arithmetic before the rounding to a code, with a wide margin
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
        step = (self.h_max - self.h_min) * 2 * (1 / (2 * CODE_MAX) + SHADER_ERR)
        return step if terrain else 2.5 * step

    def depth_bound(self) -> float:
        """Largest decoding error (m) of a depth."""
        return (self.z_far - self.z_near) * (1 / (2 * CODE_MAX) + SHADER_ERR)


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


def pack_planes(planes: np.ndarray) -> np.ndarray:
    """Code planes (3, H, W) in G, B, R order → each pixel's codes in one word (H, W) uint32: G | B << 10 | R << 20."""
    g, b, r = (np.asarray(p, np.uint32) for p in planes)
    return g | (b << 10) | (r << 20)


def unpack_planes(words: np.ndarray) -> np.ndarray:
    """Packed codes (H, W) uint32 (``pack_planes``) → code planes (3, H, W) uint16 in G, B, R order."""
    out = np.empty((3, *words.shape), np.uint16)
    np.bitwise_and(words, CODE_MAX, out=out[0], casting="unsafe")
    np.bitwise_and(words >> 10, CODE_MAX, out=out[1], casting="unsafe")
    np.right_shift(words, 20, out=out[2], casting="unsafe")
    return out


def unpack_codes(words: np.ndarray) -> np.ndarray:
    """Packed codes (H, W) uint32 (``pack_planes``) → codes (H, W, 3) uint16 R, G, B."""
    g, b, r = unpack_planes(words)
    return np.stack((r, g, b), -1)


def _planar_frame(frame: np.ndarray, width: int, height: int, where: str) -> av.VideoFrame:
    """A gbrp10le frame of a frame's code planes (``_planes``)."""
    vf = av.VideoFrame(width, height, "gbrp10le")
    for plane, data in zip(vf.planes, _planes(frame, width, height, where)):  # gbrp: planes G, B, R
        dst = np.frombuffer(plane, np.uint16).reshape(height, plane.line_size // 2)
        dst[:, :width] = data
    return vf


def _planes(frame: np.ndarray, width: int, height: int, where: str) -> np.ndarray:
    """Code planes (3, H, W) uint16 in G, B, R order of a frame in any form ``write_gbuffer`` takes."""
    if frame.dtype == np.uint32 and frame.shape == (height, width):
        return unpack_planes(frame)
    if frame.dtype != np.uint16:
        frame = to_codes(frame)
    if frame.shape == (3, height, width):
        return frame
    if frame.shape == (height, width, 3):
        return np.stack((frame[..., 1], frame[..., 2], frame[..., 0]))
    raise ValueError(
        f"{where}: frame is {frame.shape} {frame.dtype}, expected {(height, width, 3)}, {(3, height, width)} uint16 "
        f"or {(height, width)} uint32"
    )


def _packed(frame: np.ndarray, width: int, height: int, where: str) -> np.ndarray:
    """A frame's packed codes (H, W) uint32 (``pack_planes``): packed frames are returned as they are."""
    if frame.dtype == np.uint32 and frame.shape == (height, width):
        return frame
    return pack_planes(_planes(frame, width, height, where))


# Below this many pixels a frame, handing each frame to the encoder thread costs more than the overlap saves: at
# 36 × 64 the two threads trade the GIL on every frame and the pass takes 2.5× the serial loop's time; from 72 × 128
# up they are even or the overlap wins (docs/tradeoffs.md, "The bridge: the encoder on a thread of its own").
OVERLAP_MIN_PIXELS = 72 * 128

GBZ_MAGIC = b"MGBZ\r\n\x1a\n"  # a .gbz file's first bytes (a line-ending or text-mode copy breaks them)
GBZ_LEVEL = -1  # zstd's level: a fast level, a fifth less CPU than level 1 for 8 % more bytes (docs/tradeoffs.md)
GBZ_END = 0xFFFFFFFF  # in place of a frame's length: the frames are over, the count follows
MAX_META_BYTES = 4096  # a .gbz file's metadata JSON is about 150 bytes
MAX_FRAME_PIXELS = 4096 * 4096  # the largest frame a reader decodes (the paper's is 704 × 1280)
_U32 = struct.Struct("<I")


def write_gbuffer(path: Path, frames: Iterable[np.ndarray], meta: GBufferMeta, overlap: bool | None = None) -> int:
    """Encode frames losslessly to ``path`` (atomic; ``.gbz`` or ``.mkv``, module docstring); returns the frame
    count. A frame is rendered floats (H, W, 3), 10-bit codes (H, W, 3) uint16, code planes (3, H, W) uint16 in
    G, B, R order (``Rasterizer.render_planes``), or packed codes (H, W) uint32 (``Rasterizer.render_packed``: the
    fast path, stored as they are in a ``.gbz``).

    With ``overlap`` the encoder runs on a thread of its own, fed through a short queue, while this thread
    produces the frames (the renderer's GL context stays on the thread that made it): the encoders and the GL
    read-back release the GIL, so a render + encode pass takes about the slower of the two instead of their
    sum. One encoder consumes the frames in order, so the bytes are those of the serial loop. The default
    (None) overlaps the FFV1 encoding of frames of at least ``OVERLAP_MIN_PIXELS`` pixels; a ``.gbz`` frame's zstd
    costs a fraction of its render, less than handing it to a second thread costs in CPU time, and is encoded on
    this thread."""
    path = Path(path)
    if path.suffix not in (".gbz", ".mkv"):
        raise ValueError(f"{path}: a G-buffer file is .gbz (the corpus's encoding) or .mkv (FFV1, for players)")
    if overlap is None:
        overlap = path.suffix == ".mkv" and meta.width * meta.height >= OVERLAP_MIN_PIXELS
    run = _encode_overlapped if overlap else _encode_serially
    with atomic_path(path) as tmp:
        if path.suffix == ".gbz":
            with open(tmp, "wb") as fh:
                n = run(frames, _gbz_encoder(fh, meta, str(path)))
                fh.write(_U32.pack(GBZ_END) + _U32.pack(n))
        else:
            # bitexact: no random segment UID or encoder string, so a re-render is byte-identical
            with av.open(str(tmp), "w", format="matroska", options={"fflags": "+bitexact"}) as c:
                n = run(frames, _ffv1_encoder(c, meta, str(path)))
    return n


def _gbz_encoder(fh, meta: GBufferMeta, where: str):
    """``encode(frame, n)`` appending frame ``n`` to an open .gbz file (its header written here); None ends it."""
    head = json.dumps(asdict(meta), sort_keys=True).encode()
    fh.write(GBZ_MAGIC + _U32.pack(len(head)) + head)
    codec = pa.Codec("zstd", compression_level=GBZ_LEVEL)

    def encode(f: np.ndarray | None, n: int) -> None:
        if f is not None:
            words = np.ascontiguousarray(_packed(f, meta.width, meta.height, f"{where}: frame {n}"), "<u4")
            block = codec.compress(words.reshape(-1).view(np.uint8), asbytes=True)
            fh.write(_U32.pack(len(block)) + block)

    return encode


def _ffv1_encoder(c, meta: GBufferMeta, where: str):
    """``encode(frame, n)`` muxing frame ``n`` into an open Matroska container (its stream added here); None flushes."""
    c.metadata[TAG] = json.dumps(asdict(meta), sort_keys=True)
    s = c.add_stream("ffv1", rate=Fraction(meta.fps).limit_denominator(1001))
    s.width, s.height, s.pix_fmt = meta.width, meta.height, "gbrp10le"
    s.options = {"level": "3", "g": "1", "slicecrc": "1"}
    s.thread_count = 1

    def encode(f: np.ndarray | None, n: int) -> None:
        frame = None if f is None else _planar_frame(f, meta.width, meta.height, f"{where}: frame {n}")
        for p in s.encode(frame):
            c.mux(p)

    return encode


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


# -- reading: both encodings, from a path or from a file's bytes (a webdataset member) --------------------


def _open(data: Path | bytes, name: str | None) -> tuple[BinaryIO, str, int]:
    """(binary file, what errors call it, its size) of a path or a file's bytes; a FIFO or device is refused."""
    if isinstance(data, bytes | bytearray | memoryview):
        return io.BytesIO(data), name or "<bytes>", len(data)
    size = regular_file(Path(data)).st_size  # a FIFO would block the reader
    return open(data, "rb"), name or str(data), size


def _meta(raw: bytes | str, where: str) -> GBufferMeta:
    """The metadata of a G-buffer file from its JSON, every field checked."""
    d = loads_json(raw, f"{where}: G-buffer metadata")
    if not isinstance(d, dict):
        raise ValueError(f"{where}: G-buffer metadata is not a JSON object")
    if d.get("version") != GBUFFER_VERSION:
        raise ValueError(f"{where}: G-buffer version {d.get('version')!r}, this reader knows {GBUFFER_VERSION}")
    fields = {f.name for f in dataclasses.fields(GBufferMeta)}
    if set(d) != fields:
        raise ValueError(f"{where}: G-buffer metadata holds {sorted(d)}, expected {sorted(fields)}")
    for k in ("width", "height"):
        if type(d[k]) is not int or d[k] < 1:
            raise ValueError(f"{where}: G-buffer {k} {d[k]!r} is not a positive integer")
    if d["width"] * d["height"] > MAX_FRAME_PIXELS:
        raise ValueError(f"{where}: G-buffer frames of {d['height']}×{d['width']}, over {MAX_FRAME_PIXELS} pixels")
    for k in ("h_min", "h_max", "z_near", "z_far", "fps"):
        if type(d[k]) not in (int, float) or not np.isfinite(d[k]):
            raise ValueError(f"{where}: G-buffer {k} {d[k]!r} is not a finite number")
    if not (d["h_min"] < d["h_max"] and 0 <= d["z_near"] < d["z_far"] and d["fps"] > 0):
        raise ValueError(
            f"{where}: G-buffer ranges out of order (h {d['h_min']}..{d['h_max']}, z {d['z_near']}..{d['z_far']}, fps {d['fps']})"
        )
    return GBufferMeta(**d)


def _read_exactly(fh: BinaryIO, n: int, where: str, what: str) -> bytes:
    data = fh.read(n)
    if len(data) != n:
        raise ValueError(f"{where}: the file ends inside {what} ({len(data)} of {n} bytes)")
    return data


def _gbz_header(fh: BinaryIO, where: str) -> GBufferMeta:
    if fh.read(len(GBZ_MAGIC)) != GBZ_MAGIC:
        raise ValueError(f"{where}: not a .gbz G-buffer file")
    (length,) = _U32.unpack(_read_exactly(fh, 4, where, "the header"))
    if length > MAX_META_BYTES:
        raise ValueError(f"{where}: a {length}-byte G-buffer header, over {MAX_META_BYTES}")
    return _meta(_read_exactly(fh, length, where, "the header"), where)


def _gbz_words(fh: BinaryIO, size: int, where: str) -> Iterator[np.ndarray]:
    """The packed codes (H, W) uint32 of each frame of an open .gbz file of ``size`` bytes, every length checked
    before it is read and every frame's size after it is inflated."""
    meta = _gbz_header(fh, where)
    shape = (meta.height, meta.width)
    raw = 4 * shape[0] * shape[1]
    codec = pa.Codec("zstd")
    n = 0
    while True:
        (length,) = _U32.unpack(_read_exactly(fh, 4, where, f"frame {n}'s length"))
        if length == GBZ_END:
            (count,) = _U32.unpack(_read_exactly(fh, 4, where, "the frame count"))
            if count != n or fh.tell() != size:
                raise ValueError(f"{where}: the file ends with a count of {count} frames after {n} of them")
            return
        if length > min(size - fh.tell(), raw + raw // 128 + 4096):  # zstd never grows a frame by more
            raise ValueError(f"{where}: frame {n} declares {length} bytes, more than the file or its frame size allows")
        block = _read_exactly(fh, length, where, f"frame {n}")
        try:
            words = codec.decompress(block, decompressed_size=raw, asbytes=True)
        except OSError as exc:
            raise ValueError(f"{where}: frame {n} does not inflate to {shape} codes ({exc})") from None
        yield np.frombuffer(words, "<u4").reshape(shape)
        n += 1


def _is_gbz(fh: BinaryIO) -> bool:
    head = fh.read(len(GBZ_MAGIC))
    fh.seek(0)
    return head == GBZ_MAGIC


def read_gbuffer_meta(path: Path | bytes, name: str | None = None) -> GBufferMeta:
    """The metadata of a G-buffer file (a path, or its bytes, called ``name`` in errors); a clear error if it is not one."""
    fh, where, _ = _open(path, name)
    with fh:
        if _is_gbz(fh):
            return _gbz_header(fh, where)
        try:
            with av.open(fh) as c:
                raw = c.metadata.get(TAG)
        except (av.error.FFmpegError, OSError) as err:
            raise ValueError(f"{where}: cannot open as a G-buffer video: {err}") from err
    if raw is None:
        raise ValueError(f"{where}: no {TAG} metadata: not a Marionette G-buffer video")
    return _meta(raw, where)


def iter_planes(path: Path | bytes, name: str | None = None) -> Iterator[np.ndarray]:
    """The code planes (3, H, W) uint16 in G, B, R order of each frame of a G-buffer file (a path or its bytes)."""
    return _decoded(path, name, unpack_planes, lambda codes: np.stack((codes[..., 1], codes[..., 2], codes[..., 0])))


def iter_codes(path: Path | bytes, name: str | None = None) -> Iterator[np.ndarray]:
    """The 10-bit codes (H, W, 3) uint16 R, G, B of each frame of a G-buffer file (a path or its bytes)."""
    return _decoded(path, name, unpack_codes, lambda codes: codes)


def _decoded(path: Path | bytes, name: str | None, from_words, from_codes) -> Iterator[np.ndarray]:
    """Each frame of either encoding: a ``.gbz`` frame's packed words through ``from_words``, an FFV1 frame's codes
    (H, W, 3) through ``from_codes``."""
    fh, where, size = _open(path, name)
    with fh:
        if _is_gbz(fh):
            for words in _gbz_words(fh, size, where):
                yield from_words(words)
        else:
            for codes in _ffv1_codes(fh, where):
                yield from_codes(codes)


def _ffv1_codes(fh: BinaryIO, where: str) -> Iterator[np.ndarray]:
    try:
        c = av.open(fh)
    except (av.error.FFmpegError, OSError) as err:
        raise ValueError(f"{where}: cannot open as a G-buffer video: {err}") from err
    with c:
        if not c.streams.video:
            raise ValueError(f"{where}: no video stream")
        s = c.streams.video[0]
        if s.codec_context.pix_fmt != "gbrp10le":
            raise ValueError(f"{where}: pixel format {s.codec_context.pix_fmt}, a G-buffer is gbrp10le")
        for frame in c.decode(s):
            yield frame.to_ndarray(format="gbrp10le")


def decode_gbuffer(path: Path) -> tuple[list[GBufferFrame], GBufferMeta]:
    """Decode a G-buffer file: per frame height, id, inv_depth (and depth), and its metadata."""
    meta = read_gbuffer_meta(path)
    return [decode_codes(c, meta) for c in iter_codes(path)], meta
