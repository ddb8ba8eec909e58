"""The video models' chunk arithmetic (``marionette.chunks``): clips of 4k + 1 frames, relay chunks that share one
frame, and the counts a relay derives from them agree with each other."""

from __future__ import annotations

from marionette.chunks import is_clip_length, relay_chunks, relay_frames, relay_starts, relay_step


def test_clip_lengths_are_4k_plus_1_from_a_minimum():
    assert [n for n in range(0, 30) if is_clip_length(n)] == [5, 9, 13, 17, 21, 25, 29]
    assert [n for n in range(0, 10) if is_clip_length(n, minimum=1)] == [1, 5, 9]


def test_relay_chunks_share_one_frame_and_cover_1_plus_n_steps():
    for T in (5, 9, 81):
        assert relay_step(T) == T - 1
        for n in range(1, 6):
            frames = relay_frames(n, T)
            assert frames == 1 + n * (T - 1)
            assert relay_chunks(frames, T) == n and relay_chunks(frames + T - 2, T) == n  # one short of another chunk
            starts = list(relay_starts(frames, T))
            assert len(starts) == n and starts[-1] + T == frames  # the last chunk ends on the last frame
            assert all(b - a == T - 1 for a, b in zip(starts, starts[1:]))
