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
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
from av.video.reformatter import VideoReformatter

from marionette.corpus import video_shards
from marionette.io import regular_file
from marionette.recordings.errors import SampleError, regular_input


@dataclass(frozen=True)
class VideoSettings:
    """Training-resolution video chunks: size (height, width), frames per chunk, x264 quality."""

    height: int = 176
    width: int = 320
    chunk_frames: int = 81
    crf: int = 20
    preset: str = "veryfast"

    def key(self) -> str:
        return f"{self.height}x{self.width}-{self.chunk_frames}f-crf{self.crf}-{self.preset}"


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
    """``x264-params`` of every RGB chunk: one thread, one lookahead thread, no sliced threads, and
    the CPU code paths of ``x264_cpu_flags`` — the same frames always give the same bytes."""
    return f"threads=1:lookahead-threads=1:sliced-threads=0:asm={x264_cpu_flags()}"


def encode_mp4(frames: np.ndarray, fps: float, settings: VideoSettings, params: str | None = None) -> bytes:
    """Encode (T, H, W, 3) uint8 RGB frames as an H.264 mp4 in memory, deterministically with the default
    ``params`` (``x264_params()``; the benchmark passes others to measure them)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or not len(frames):
        raise ValueError(f"encode_mp4: expected (T, H, W, 3) uint8 frames with T > 0, got {frames.shape} {frames.dtype}")
    buf = io.BytesIO()
    options = {"crf": str(settings.crf), "preset": settings.preset, "x264-params": params or x264_params()}
    with av.open(buf, "w", format="mp4") as c:
        s = c.add_stream("libx264", rate=int(round(fps)), options=options)
        s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        s.codec_context.thread_count = 1
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return buf.getvalue()


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


def _open_video(path: Path) -> av.container.InputContainer:
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
    decoded once, sequentially. Returns the json records written.
    """
    wanted: dict[int, list[tuple[str, int]]] = {}
    plan: list[tuple[str, int, int, int, np.ndarray]] = []
    for seg, a, b, K in segments:
        for ci, (s, e) in enumerate(chunk_spans(b - a, settings.chunk_frames)):
            plan.append((seg, ci, a + s, a + e, K[s:e]))
            for f in range(a + s, a + e):
                wanted.setdefault(f, []).append((seg, ci))
    records: list[dict] = []
    buffers: dict[tuple[str, int], list[np.ndarray]] = {(p[0], p[1]): [] for p in plan}
    with video_shards.writer(out) as tar:
        if plan:
            with _open_video(rgb_path) as c:
                s = c.streams.video[0]
                s.codec_context.thread_count = 1  # one codec thread: parallelism comes from workers
                src_h, src_w = s.codec_context.height, s.codec_context.width
                cr = CropResize.fit(src_h, src_w, settings.height, settings.width)
                x0, y0, cw, ch = cr.x0, cr.y0, cr.w, cr.h
                pending = {(p[0], p[1]): p for p in plan}
                last = max(wanted)
                to_rgb, to_size = VideoReformatter(), VideoReformatter()  # one swscale context each for the stream
                frames = c.decode(s)
                i = -1
                while True:
                    try:
                        fr = next(frames)
                    except StopIteration:
                        break
                    except av.error.FFmpegError as exc:
                        raise SampleError(f"{rgb_path}: cannot decode frame {i + 1}: {exc}") from None
                    i += 1
                    if i not in wanted:
                        if i > last:
                            break
                        continue
                    try:
                        img = to_rgb.reformat(fr, format="rgb24").to_ndarray()[y0 : y0 + ch, x0 : x0 + cw]
                        crop = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
                        small = to_size.reformat(
                            crop, width=settings.width, height=settings.height, interpolation="AREA"
                        ).to_ndarray()
                    except (av.error.FFmpegError, ValueError) as exc:
                        raise SampleError(f"{rgb_path}: cannot convert frame {i}: {type(exc).__name__}: {exc}") from None
                    for key in wanted[i]:
                        buffers[key].append(small)
                        seg, ci, a, b, K = pending[key]
                        if len(buffers[key]) == b - a:
                            rec = {
                                **meta,
                                "segment": seg,
                                "chunk": ci,
                                "frames": [a, b],
                                "fps": fps,
                                "source_size": [src_h, src_w],
                                "crop": cr.to_json(),
                                "resize": [settings.height, settings.width],
                                "scale": [cr.sy, cr.sx],
                                "K": np.round(cr.intrinsics(K), 6).tolist(),
                            }
                            mp4 = encode_mp4(np.stack(buffers.pop(key)), fps, settings)
                            key = video_shards.chunk_key(seg, ci)
                            video_shards.add_member(tar, video_shards.member_name(key, video_shards.RGB_KIND), mp4)
                            video_shards.add_member(
                                tar, video_shards.member_name(key, "json"), json.dumps(rec, sort_keys=True).encode()
                            )
                            records.append(rec)
                if buffers:
                    (seg, ci), got = next(iter(buffers.items()))
                    first_missing = pending[(seg, ci)][2] + len(got)
                    raise SampleError(f"{rgb_path}: video ends before frame {first_missing} (needed for chunk {ci} of {seg})")
    return records
