"""Byte-identical rebuilds: the same recordings give the same corpus, every file, RGB chunks included."""

from __future__ import annotations

import hashlib
from pathlib import Path

import av
import numpy as np

from marionette.ingest import IngestOptions, build_corpus
from marionette.video import CropResize, VideoSettings, chunk_spans, encode_mp4


def _tree(root: Path) -> dict[str, bytes | None]:
    """Relative path → bytes (None for a directory) of everything under ``root``."""
    return {p.relative_to(root).as_posix(): (None if p.is_dir() else p.read_bytes()) for p in sorted(root.rglob("*"))}


def test_the_same_frames_encode_to_the_same_bytes_every_time(synth_source):
    # the chunks of one recording at the default training size, as ingest makes them, encoded three times
    # over in one process: x264's AVX-512 macroblock-tree code gave the first chunk other bytes the second time
    cr = CropResize.fit(90, 160, 176, 320)
    with av.open(str(synth_source / "data_part1" / "rec0000" / "rgb.mp4")) as c:
        frames = [f.to_ndarray(format="rgb24")[cr.y0 : cr.y0 + cr.h, cr.x0 : cr.x0 + cr.w] for f in c.decode(video=0)]
    assert frames[0].shape[:2] == (88, 160)  # the session source's 160 × 90, cropped to the training aspect
    small = np.stack(
        [
            av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="rgb24")
            .reformat(width=320, height=176, interpolation="AREA")
            .to_ndarray(format="rgb24")
            for f in frames
        ]
    )
    chunks = [small[a:b] for a, b in chunk_spans(len(small), 81)]
    rounds = [[hashlib.sha256(encode_mp4(ch, 30.0, VideoSettings())).hexdigest() for ch in chunks] for _ in range(3)]
    assert rounds[0] == rounds[1] == rounds[2]


def test_two_clean_builds_are_byte_identical(synth_source, tmp_path):
    options = IngestOptions()  # the default video settings: 320 × 176, crf 20
    for name in ("a", "b"):
        build_corpus(synth_source, tmp_path / name, options, workers=2, progress=False)
    a, b = _tree(tmp_path / "a"), _tree(tmp_path / "b")
    assert a and a.keys() == b.keys()
    lock = "meta/.lock"
    assert a.get(lock) == b.get(lock) == b"", "the lock is empty between builds"
    differ = sorted(k for k in a if a[k] != b[k])
    assert not differ, f"files that differ between two clean builds: {differ}"
    assert any(k.startswith("video/") and k.endswith(".tar") for k in a)
