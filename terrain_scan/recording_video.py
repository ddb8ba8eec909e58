"""A recording's videos as the scan reads them: the depth frames it keeps (and only those decoded where the codec
allows), and the recording's time from rgb.mp4's container."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator
from pathlib import Path

import av
import numpy as np
from av.video.reformatter import VideoReformatter

from marionette.recordings.errors import SampleError
from marionette.video import open_video


def recording_time(rgb_path: Path) -> int:
    """Unix seconds of a recording from ``creation_time`` (ISO 8601) in rgb.mp4's container metadata; 0 if absent."""
    try:
        with av.open(str(rgb_path)) as c:
            s = c.metadata.get("creation_time") or (c.streams.video[0].metadata.get("creation_time") if c.streams.video else None)
    except (av.error.FFmpegError, FileNotFoundError):
        return 0
    if not s:
        return 0
    try:
        t = dt.datetime.fromisoformat(s.strip().replace("Z", "+00:00"))
    except ValueError:
        return 0
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return max(0, int(t.timestamp()))


def depth_frames(path: Path, keep: Callable[[int], bool] | None = None) -> Iterator[np.ndarray | None]:
    """The frames of an 8-bit depth video in display order, as (H, W) uint8 codes (one decoder thread).

    With ``keep``, frame i is None where ``keep(i)`` is false: not converted, and not decoded at all where the
    decoder can leave it out (a frame no other frame is predicted from); the frames kept decode to the very
    bytes a full decode gives. A frame's place i is then its timestamp's rank among the stream's packets
    (``display_ranks``). A file that does not open or decode as a video raises SampleError naming it and the
    frame."""
    ranks = display_ranks(path) if keep is not None else None
    c = open_video(path)
    with c:
        s = c.streams.video[0]
        s.thread_count = 1
        gray = VideoReformatter()  # one swscale context for the stream (a frame's own ``to_ndarray`` makes one per frame)
        i = 0  # the next frame's place
        for packet in c.demux(s):
            if ranks is not None and packet.pts in ranks:
                s.codec_context.skip_frame = "DEFAULT" if keep(ranks[packet.pts]) else "NONREF"
            try:
                frames = s.decode(packet)
            except (av.error.FFmpegError, ValueError) as exc:
                raise SampleError(f"{path}: cannot decode frame {i}: {type(exc).__name__}: {exc}") from None
            for frame in frames:
                at = ranks.get(frame.pts, i) if ranks is not None else i
                for _ in range(i, at):  # left out by the decoder
                    yield None
                i = at
                if keep is not None and not keep(i):
                    yield None
                else:
                    try:
                        yield gray.reformat(frame, format="gray").to_ndarray()  # a gray frame is returned as it is
                    except (av.error.FFmpegError, ValueError) as exc:
                        raise SampleError(f"{path}: cannot decode frame {i}: {type(exc).__name__}: {exc}") from None
                i += 1


def display_ranks(path: Path) -> dict[int, int] | None:
    """Each video packet's timestamp → its frame's place in display order (the timestamp's rank), read in one pass
    over the container; None where a packet has no timestamp, two share one, or the container does not read
    through (``depth_frames`` then decodes every frame and counts them)."""
    try:
        with av.open(str(path)) as c:
            pts = [p.pts for p in c.demux(c.streams.video[0]) if p.size]
    except (av.error.FFmpegError, IndexError, ValueError):
        return None
    if any(t is None for t in pts) or len(set(pts)) != len(pts):
        return None
    return {t: k for k, t in enumerate(sorted(pts))}
