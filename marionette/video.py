"""The project's video codec (PyAV): chunk spans, crop and resize to the training aspect, H.264 chunks for the
webdataset shards (deterministic encoder settings), decoding, and the video shard writer.

Image coordinates are continuous: pixel (i, j) covers [j, j+1) × [i, i+1), so a centred principal
point is cx = W/2. Cropping x0 columns and scaling by s maps fx → s·fx and cx → s·(cx − x0).
"""

from __future__ import annotations

import functools
import io
import json
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
from av.video.reformatter import VideoReformatter

from marionette.corpus import video_shards
from marionette.io import regular_file
from marionette.recordings.errors import SampleError, regular_input

# x264 options over the preset: superfast's motion search and partitions with veryfast's rate control (mb-tree over a
# 10-frame lookahead). From 176 × 320 to 704 × 1280: 0.5× veryfast's encode time, PSNR within 0.25 dB, SSIM within
# 0.002, 1.1–1.15× the bytes (benchmarks/bench_rgb_chunks.py).
X264_OPTIONS = "me=dia:subme=1:partitions=i8x8,i4x4"
# From the paper's chunk size up, P-frames only: there B-frames take a quarter of the encode, the largest part of ingest
# (without them: 0.75× the time, 1.26× the bytes, PSNR and SSIM no lower); at 352 × 640 and below they cost at most
# 11 % of the encode and save a quarter of the bytes.
P_FRAMES_ONLY_PIXELS = 704 * 1280


def x264_options_for(height: int, width: int) -> str:
    """The default ``x264_options`` of chunks of this size."""
    return f"{X264_OPTIONS}:bframes=0" if height * width >= P_FRAMES_ONLY_PIXELS else X264_OPTIONS


@dataclass(frozen=True)
class VideoSettings:
    """Training-resolution video chunks: size (height, width), frames per chunk, x264 quality, speed and options
    (``x264_options``: a ``key=value:...`` list applied over the preset; by default ``x264_options_for`` the size)."""

    height: int = 176
    width: int = 320
    chunk_frames: int = 81
    crf: int = 20
    preset: str = "veryfast"
    x264_options: str | None = None

    def __post_init__(self) -> None:
        if self.x264_options is None:  # the size's default, written out: the settings say what the chunks hold
            object.__setattr__(self, "x264_options", x264_options_for(self.height, self.width))

    def key(self) -> str:
        options = f"-{self.x264_options}" if self.x264_options else ""
        return f"{self.height}x{self.width}-{self.chunk_frames}f-crf{self.crf}-{self.preset}{options}"


@dataclass(frozen=True)
class CropResize:
    """A centred whole-pixel crop of the source to the target aspect, then a resize to the target."""

    x0: int
    y0: int
    w: int
    h: int
    out_h: int
    out_w: int

    @staticmethod
    def fit(src_h: int, src_w: int, dst_h: int, dst_w: int) -> CropResize:
        """The largest centred crop with the destination aspect (rounded to whole pixels)."""
        if src_w * dst_h >= src_h * dst_w:  # source wider: crop columns
            cw, ch = int(round(src_h * dst_w / dst_h)), src_h
        else:
            cw, ch = src_w, int(round(src_w * dst_h / dst_w))
        return CropResize((src_w - cw) // 2, (src_h - ch) // 2, cw, ch, dst_h, dst_w)

    @property
    def sx(self) -> float:
        return self.out_w / self.w

    @property
    def sy(self) -> float:
        return self.out_h / self.h

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """(…, 4) fx, fy, cx, cy in source pixels → the same in output pixels."""
        K = np.asarray(K, np.float64)
        return np.stack(
            [K[..., 0] * self.sx, K[..., 1] * self.sy, (K[..., 2] - self.x0) * self.sx, (K[..., 3] - self.y0) * self.sy], -1
        )

    def to_json(self) -> dict:
        return {"x0": self.x0, "y0": self.y0, "w": self.w, "h": self.h, "out_h": self.out_h, "out_w": self.out_w}


def chunk_spans(n_frames: int, chunk: int) -> list[tuple[int, int]]:
    """Chunks [start, stop) covering a segment: stride ``chunk``, the last one aligned to the end.

    A segment shorter than one chunk gives no chunk.
    """
    if n_frames < chunk:
        return []
    starts = list(range(0, n_frames - chunk + 1, chunk))
    if starts[-1] + chunk < n_frames:
        starts.append(n_frames - chunk)
    return [(s, s + chunk) for s in starts]


@functools.cache
def x264_cpu_flags() -> str:
    """The CPU capabilities this process's libx264 detects, minus AVX-512, as its ``asm`` option.

    With its AVX-512 code x264 is not deterministic: the same frames, encoded again in the same
    process, gave another bitstream (decoded frames tens of levels apart), so two builds of the same
    recordings differed; without it (and with ``mbtree=0`` or ``asm=0``) they never did. Every other
    code path x264 detects is kept, so the encode is as fast as before. x264 reports what it
    detected when an encoder opens (``using cpu capabilities: ...``); it trusts an ``asm`` list
    blindly, so the list is only ever what it found itself. Where that line cannot be read, the
    answer is ``"0"`` (plain C: deterministic, ~4× slower).
    """
    prev = av.logging.get_level()
    av.logging.set_level(av.logging.INFO)
    try:
        with av.logging.Capture() as logs:
            cc = av.CodecContext.create("libx264", "w")
            cc.width, cc.height, cc.pix_fmt = 16, 16, "yuv420p"
            cc.time_base = Fraction(1, 30)
            cc.open()
            del cc
    finally:
        av.logging.set_level(prev)
    for _, name, message in logs:
        if name == "libx264" and message.startswith("using cpu capabilities:"):
            flags = message.split(":", 1)[1].split()
            if flags == ["none!"]:
                return "0"
            return ",".join(f for f in flags if f.upper() != "AVX512") or "0"
    warnings.warn("libx264 did not report its CPU capabilities: encoding without assembly (slower)", stacklevel=2)
    return "0"


def x264_params() -> str:
    """The ``x264-params`` every RGB chunk ends with: one thread, one lookahead thread, no sliced threads, and the CPU
    code paths of ``x264_cpu_flags`` — the same frames always give the same bytes."""
    return f"threads=1:lookahead-threads=1:sliced-threads=0:asm={x264_cpu_flags()}"


def chunk_x264_params(settings: VideoSettings) -> str:
    """``x264-params`` of a chunk: the settings' ``x264_options``, then ``x264_params()`` (last: nothing overrides it)."""
    return ":".join(p for p in (settings.x264_options, x264_params()) if p)


class ChunkEncoder:
    """One H.264 mp4 in memory, fed yuv420p frames of one size one at a time; ``finish`` returns its bytes.

    ``params`` replaces ``chunk_x264_params(settings)`` (the benchmarks measure others); ``colour`` tags the stream
    (``colorspace``, ``color_range``, ``color_primaries``, ``color_trc``) so a decoder turns it into the RGB its source
    gave.
    """

    def __init__(
        self, width: int, height: int, fps: float, settings: VideoSettings, params: str | None = None, colour: dict | None = None
    ):
        self._buf = io.BytesIO()
        self._mp4 = av.open(self._buf, "w", format="mp4")
        options = {"crf": str(settings.crf), "preset": settings.preset, "x264-params": params or chunk_x264_params(settings)}
        self._rate = int(round(fps))
        self._stream = self._mp4.add_stream("libx264", rate=self._rate, options=options)
        self._stream.width, self._stream.height, self._stream.pix_fmt = width, height, "yuv420p"
        self._stream.codec_context.thread_count = 1
        for name, value in (colour or {}).items():
            setattr(self._stream.codec_context, name, value)
        self.frames = 0

    def add(self, frame: av.VideoFrame) -> None:
        """Encode the next frame (its timestamp is set here: frame n of the chunk at ``fps``)."""
        frame.pts, frame.time_base = self.frames, Fraction(1, self._rate)
        for packet in self._stream.encode(frame):
            self._mp4.mux(packet)
        self.frames += 1

    def finish(self) -> bytes:
        """Flush the encoder, close the mp4 and return its bytes."""
        for packet in self._stream.encode():
            self._mp4.mux(packet)
        self._mp4.close()
        return self._buf.getvalue()

    def close(self) -> None:
        """Drop an unfinished chunk."""
        self._mp4.close()


def encode_mp4(frames: np.ndarray, fps: float, settings: VideoSettings, params: str | None = None) -> bytes:
    """Encode (T, H, W, 3) uint8 RGB frames as an H.264 mp4 in memory, deterministically with the default
    ``params`` (``chunk_x264_params(settings)``; the benchmarks pass others to measure them)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or not len(frames):
        raise ValueError(f"encode_mp4: expected (T, H, W, 3) uint8 frames with T > 0, got {frames.shape} {frames.dtype}")
    to_yuv = VideoReformatter()
    encoder = ChunkEncoder(frames.shape[2], frames.shape[1], fps, settings, params)
    try:
        for f in frames:
            encoder.add(to_yuv.reformat(av.VideoFrame.from_ndarray(f, format="rgb24"), format="yuv420p", threads=1))
    except BaseException:
        encoder.close()
        raise
    return encoder.finish()


def decode_frames(path_or_bytes, indices: set[int] | None = None) -> dict[int, np.ndarray] | list[np.ndarray]:
    """Decode RGB frames; all as a list, or only ``indices`` as {frame: array}."""
    if isinstance(path_or_bytes, bytes | bytearray):
        src = io.BytesIO(path_or_bytes)
    else:
        regular_file(Path(path_or_bytes))  # a FIFO would block the decoder
        src = str(path_or_bytes)
    out_d: dict[int, np.ndarray] = {}
    out_l: list[np.ndarray] = []
    rgb = VideoReformatter()  # one swscale context for the stream (a frame's own ``to_ndarray`` makes one per frame)
    with av.open(src) as c:
        s = c.streams.video[0]
        s.codec_context.thread_count = 1
        for i, fr in enumerate(c.decode(s)):
            if indices is None:
                out_l.append(rgb.reformat(fr, format="rgb24").to_ndarray())
            elif i in indices:
                out_d[i] = rgb.reformat(fr, format="rgb24").to_ndarray()
                if len(out_d) == len(indices):
                    break
    return out_l if indices is None else out_d


def open_video(path: Path) -> av.container.InputContainer:
    """Open a video with at least one video stream; anything else raises SampleError naming the file."""
    regular_input(Path(path))
    try:
        c = av.open(str(path))
    except av.error.FFmpegError as exc:
        raise SampleError(f"{path}: unreadable video ({type(exc).__name__}: {exc})") from None
    if not c.streams.video:
        c.close()
        raise SampleError(f"{path}: no video stream")
    return c


@dataclass(frozen=True)
class _Chunk:
    """One chunk of the shard: segment, chunk number, source frames [start, stop), intrinsics (n, 4) in source pixels."""

    segment: str
    number: int
    start: int
    stop: int
    K: np.ndarray


def _chunk_plan(segments: list[tuple[str, int, int, np.ndarray]], chunk_frames: int) -> list[_Chunk]:
    """Every segment's chunks (``chunk_spans``), in segment order."""
    return [
        _Chunk(seg, ci, a + s, a + e, K[s:e])
        for seg, a, b, K in segments
        for ci, (s, e) in enumerate(chunk_spans(b - a, chunk_frames))
    ]


COLOUR_TAGS = ("colorspace", "color_range", "color_primaries", "color_trc")  # how a decoder turns YUV into RGB


def crop_planes(frame: av.VideoFrame, x0: int, y0: int, w: int, h: int) -> av.VideoFrame:
    """The (x0, y0, w, h) window of a yuv420p frame, plane by plane, as a new frame with the same colour tags; the
    window's offsets and sizes are even, so the chroma planes (half the size) crop exactly."""
    out = av.VideoFrame(w, h, "yuv420p")
    for i, (src, dst) in enumerate(zip(frame.planes, out.planes)):
        k = 1 if i else 0  # chroma planes: half the rows and columns
        rows = np.frombuffer(src, np.uint8).reshape(src.height, src.line_size)
        np.frombuffer(dst, np.uint8).reshape(dst.height, dst.line_size)[:, : w >> k] = rows[
            y0 >> k : (y0 + h) >> k, x0 >> k : (x0 + w) >> k
        ]
    for tag in COLOUR_TAGS:
        setattr(out, tag, getattr(frame, tag))
    return out


class ChunkFrames:
    """Decoded source frames → the chunk's yuv420p frames (``CropResize``), as the encoder takes them.

    A yuv420p source whose crop window lies on even pixels (every 16:9 source at the 11:20 training aspect) is cropped
    plane by plane, exactly, and resampled (AREA, in yuv420p) only when the crop's size is not the chunk's: no RGB round
    trip, and its colour tags go with it (``colour``). Any other source takes the reference route: RGB24, crop, then one
    swscale call to the chunk's size in yuv420p (BT.601, untagged).
    """

    def __init__(self, cr: CropResize, source: av.VideoCodecContext):
        self.cr = cr
        self.planar = source.pix_fmt == "yuv420p" and all(v % 2 == 0 for v in (cr.x0, cr.y0, cr.w, cr.h))
        self.colour = {t: getattr(source, t) for t in COLOUR_TAGS} if self.planar else {}
        self._to_rgb, self._to_chunk = VideoReformatter(), VideoReformatter()  # one swscale context each for the stream

    def __call__(self, frame: av.VideoFrame) -> av.VideoFrame:
        cr = self.cr
        if self.planar and frame.format.name == "yuv420p":
            window = crop_planes(frame, cr.x0, cr.y0, cr.w, cr.h)
            if (cr.h, cr.w) == (cr.out_h, cr.out_w):
                return window
        else:
            rgb = self._to_rgb.reformat(frame, format="rgb24", threads=1).to_ndarray()
            window = av.VideoFrame.from_ndarray(
                np.ascontiguousarray(rgb[cr.y0 : cr.y0 + cr.h, cr.x0 : cr.x0 + cr.w]), format="rgb24"
            )
        return self._to_chunk.reformat(window, width=cr.out_w, height=cr.out_h, format="yuv420p", interpolation="AREA", threads=1)


def _decoded(c: av.container.InputContainer, path: Path) -> Iterator[tuple[int, av.VideoFrame]]:
    """(number, frame) of the first video stream, on one codec thread; a frame that cannot be decoded or whose size is
    not the stream's is a SampleError naming the file and the frame."""
    s = c.streams.video[0]
    s.codec_context.thread_count = 1  # one codec thread: parallelism comes from workers
    size = (s.codec_context.width, s.codec_context.height)
    frames = c.decode(s)
    i = 0
    while True:
        try:
            fr = next(frames)
        except StopIteration:
            return
        except av.error.FFmpegError as exc:
            raise SampleError(f"{path}: cannot decode frame {i}: {exc}") from None
        if (fr.width, fr.height) != size:
            raise SampleError(f"{path}: frame {i} is {fr.width}×{fr.height}, the stream's frames are {size[0]}×{size[1]}")
        yield i, fr
        i += 1


def _chunk_record(chunk: _Chunk, fps: float, source_size: tuple[int, int], cr: CropResize, meta: dict) -> dict:
    """A chunk's json member: where it comes from, how it was cropped and resized, its intrinsics in chunk pixels."""
    return {
        **meta,
        "segment": chunk.segment,
        "chunk": chunk.number,
        "frames": [chunk.start, chunk.stop],
        "fps": fps,
        "source_size": list(source_size),
        "crop": cr.to_json(),
        "resize": [cr.out_h, cr.out_w],
        "scale": [cr.sy, cr.sx],
        "K": np.round(cr.intrinsics(chunk.K), 6).tolist(),
    }


def _add_chunk(tar, chunk: _Chunk, mp4: bytes, record: dict) -> None:
    """A chunk's members in the shard: ``rgb.mp4``, then ``json``."""
    key = video_shards.chunk_key(chunk.segment, chunk.number)
    video_shards.add_member(tar, video_shards.member_name(key, video_shards.RGB_KIND), mp4)
    video_shards.add_member(tar, video_shards.member_name(key, "json"), json.dumps(record, sort_keys=True).encode())


def write_video_shard(
    out: Path,
    rgb_path: Path,
    segments: list[tuple[str, int, int, np.ndarray]],
    fps: float,
    settings: VideoSettings,
    meta: dict,
) -> list[dict]:
    """Write a webdataset tar of RGB chunks for ``segments`` [(segment id, start, stop, K (n,4))].

    Keys and members as ``marionette.corpus.video_shards`` defines them (``rgb.mp4`` and ``json``). The source is
    decoded once, sequentially; each wanted frame is made a chunk frame once (``ChunkFrames``) and fed to the encoder of
    every chunk holding it, and a chunk's members are written when its last frame is in. Returns the json records
    written, in that order.
    """
    plan = _chunk_plan(segments, settings.chunk_frames)
    wanted: dict[int, list[int]] = {}  # source frame → the chunks (indices into plan) holding it
    for k, chunk in enumerate(plan):
        for f in range(chunk.start, chunk.stop):
            wanted.setdefault(f, []).append(k)
    records: list[dict] = []
    with video_shards.writer(out) as tar:
        if not plan:
            return records
        encoders: dict[int, ChunkEncoder] = {}
        added = [0] * len(plan)
        with open_video(rgb_path) as c:
            source = c.streams.video[0].codec_context
            source_size = (source.height, source.width)
            cr = CropResize.fit(*source_size, settings.height, settings.width)
            to_chunk = ChunkFrames(cr, source)
            last = max(wanted)
            try:
                for i, frame in _decoded(c, rgb_path):
                    if i > last:
                        break
                    if i not in wanted:
                        continue
                    try:
                        small = to_chunk(frame)
                    except (av.error.FFmpegError, ValueError) as exc:
                        raise SampleError(f"{rgb_path}: cannot convert frame {i}: {type(exc).__name__}: {exc}") from None
                    for k in wanted[i]:
                        if k not in encoders:
                            encoders[k] = ChunkEncoder(cr.out_w, cr.out_h, fps, settings, colour=to_chunk.colour)
                        encoders[k].add(small)
                        added[k] += 1
                        chunk = plan[k]
                        if added[k] == chunk.stop - chunk.start:
                            records.append(_chunk_record(chunk, fps, source_size, cr, meta))
                            _add_chunk(tar, chunk, encoders.pop(k).finish(), records[-1])
            finally:
                for encoder in encoders.values():
                    encoder.close()
        short = next((k for k, chunk in enumerate(plan) if added[k] < chunk.stop - chunk.start), None)
        if short is not None:
            chunk = plan[short]
            raise SampleError(
                f"{rgb_path}: video ends before frame {chunk.start + added[short]} "
                f"(needed for chunk {chunk.number} of {chunk.segment})"
            )
    return records
