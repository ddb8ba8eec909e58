"""Chunk arithmetic of the video models, one fact in one place: a clip is T = 4k + 1 frames (the video VAEs compress
time by 4 after the first frame), and a relay paints chunk k from frame k·(T − 1), so consecutive chunks share one
frame and N chunks cover 1 + N·(T − 1) frames."""

from __future__ import annotations

TEMPORAL_STRIDE = 4


def is_clip_length(frames: int, minimum: int = 5) -> bool:
    """Whether ``frames`` is 4k + 1 and at least ``minimum``."""
    return frames >= minimum and (frames - 1) % TEMPORAL_STRIDE == 0


def relay_step(T: int) -> int:
    """Frames between the starts of consecutive relay chunks of T frames (they share one frame)."""
    return T - 1


def relay_frames(chunks: int, T: int) -> int:
    """Frames that ``chunks`` relay chunks of T frames cover, the first frame included."""
    return 1 + chunks * relay_step(T)


def relay_chunks(n_frames: int, T: int) -> int:
    """The most relay chunks of T frames that ``n_frames`` frames hold."""
    return (n_frames - 1) // relay_step(T)


def relay_starts(n_frames: int, T: int) -> range:
    """The first frame of every relay chunk of T frames that fits in ``n_frames`` frames."""
    return range(0, n_frames - T + 1, relay_step(T))


def relay_spans(n_frames: int, T: int) -> list[tuple[int, int]]:
    """Frame spans [a, b) of every relay chunk of T frames inside ``n_frames`` frames (consecutive ones share a frame)."""
    return [(s, s + T) for s in range(0, max(0, relay_chunks(n_frames, T)) * relay_step(T), relay_step(T))]
