"""Byte-identical rebuilds: the same recordings give the same corpus, every file, RGB chunks included."""

from __future__ import annotations

import hashlib
import tarfile
from pathlib import Path

import av
import numpy as np

from marionette.ingest import IngestOptions, build_corpus
from marionette.video import CropResize, VideoSettings, chunk_spans, decode_frames, encode_mp4


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


PAPER_FRAMES = 60  # frames of the paper-shaped recording: one segment, chunks [0, 25), [25, 50), [35, 60)


def _paper_shaped_source(synth_source: Path, root: Path) -> Path:
    """A WildWorld tree of one recording shaped as the paper's: the first ``PAPER_FRAMES`` frames of a session recording,
    its video scaled to 1280 × 720 with a fixed texture over it, and its depth a flat 1280 × 720 FFV1 video (ingest
    reads only depth's headers)."""
    src_part, part = synth_source / "data_part1", root / "data_part1"
    rec = part / "rec0000"
    rec.mkdir(parents=True)
    (part / "skeleton_edges.json").write_bytes((src_part / "skeleton_edges.json").read_bytes())
    lines = (src_part / "rec0000" / "state.csv").read_bytes().splitlines(keepends=True)
    (rec / "state.csv").write_bytes(b"".join(lines[: PAPER_FRAMES + 1]))
    with np.load(src_part / "rec0000" / "skeleton.npz") as z:
        np.savez(rec / "skeleton.npz", **{k: z[k][:PAPER_FRAMES] for k in z.files})
    small = decode_frames(src_part / "rec0000" / "rgb.mp4")[:PAPER_FRAMES]
    texture = np.random.default_rng(0).integers(0, 8, (720, 1280, 3), dtype=np.uint8)
    big = np.stack(
        [av.VideoFrame.from_ndarray(f, format="rgb24").reformat(1280, 720, threads=1).to_ndarray() ^ texture for f in small]
    )
    (rec / "rgb.mp4").write_bytes(encode_mp4(big, 30.0, VideoSettings(720, 1280, preset="ultrafast", x264_options="")))
    with av.open(str(rec / "depth.mkv"), "w", format="matroska") as c:
        s = c.add_stream("ffv1", rate=30)
        s.width, s.height, s.pix_fmt = 1280, 720, "gray"
        for i in range(PAPER_FRAMES):
            frame = av.VideoFrame.from_ndarray(np.zeros((720, 1280), np.uint8), format="gray")
            frame.pts = i
            for p in s.encode(frame):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return root


def test_two_clean_builds_at_the_papers_size_are_byte_identical(synth_source, tmp_path):
    # 704 × 1280 chunks from a 720 × 1280 source: the crop is 8 rows off each edge and no resize, the path the
    # paper's corpus takes (the default-size test above resizes)
    src = _paper_shaped_source(synth_source, tmp_path / "src")
    options = IngestOptions(video=VideoSettings(height=704, width=1280, chunk_frames=25))
    for name in ("a", "b"):
        build_corpus(src, tmp_path / name, options, progress=False)
    a, b = _tree(tmp_path / "a"), _tree(tmp_path / "b")
    differ = sorted(k for k in a if a[k] != b.get(k))
    assert a.keys() == b.keys() and not differ, f"files that differ between two clean builds: {differ}"
    (shard,) = [k for k in a if k.startswith("video/") and k.endswith(".tar")]
    with tarfile.open(tmp_path / "a" / shard) as tar:
        chunks = sorted(n for n in tar.getnames() if n.endswith(".rgb.mp4"))
        assert len(chunks) == 3
        first = decode_frames(tar.extractfile(chunks[0]).read())
    assert len(first) == 25 and first[0].shape == (704, 1280, 3)
