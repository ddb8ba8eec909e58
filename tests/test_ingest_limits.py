"""Limits before work and untrusted source trees: skeleton.npz members checked before they are inflated,
TRN2 sizes before their bodies are read, depth.mkv checked at ingest and caught per recording by the
terrain scan, symlinks out of the source tree refused, skipped directories listed."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tracemalloc
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fixtures.corpora import TEST_OPTIONS

from marionette.ingest import build_corpus, discover
from marionette.recordings.errors import SampleError
from marionette.recordings.skeleton_archive import SkeletonArchive
from terrain_scan.options import ScanOptions
from terrain_scan.scan import scan_stages
from terrain_scan.trn2 import Chunk, TerrainFormatError, read_chunk

NPC_KEY = "n1_0"  # the hunter's member in the synthetic recordings' skeleton.npz


def _copy_part(src: Path, dst: Path, names: dict[str, str]) -> Path:
    """Copy recordings of the session source into ``dst/data_part1`` under new names."""
    part = dst / "data_part1"
    part.mkdir(parents=True, exist_ok=True)
    shutil.copy(src / "data_part1" / "skeleton_edges.json", part)
    for old, new in names.items():
        shutil.copytree(src / "data_part1" / old, part / new)
    return part


def _write_npy_member(zf: zipfile.ZipFile, key: str, shape: tuple, dtype: str, data: bytes | int, trailing: int = 0) -> None:
    """A member ``key.npy`` with the given header; ``data`` as bytes, or that many zero bytes written in
    pieces (so a 1 GB member costs this process no memory); ``trailing`` zero bytes after it."""
    with zf.open(f"{key}.npy", "w", force_zip64=True) as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": dtype, "fortran_order": False, "shape": shape})
        if isinstance(data, bytes):
            fh.write(data)
            left = trailing
        else:
            left = data + trailing
        zero = bytes(16 << 20)
        while left > 0:
            fh.write(zero[: min(left, len(zero))])
            left -= len(zero)


def _rewrite_npz(path: Path, replace_member=None) -> dict[str, np.ndarray]:
    """Rewrite a skeleton.npz keeping its members except the one ``replace_member(zf)`` writes itself."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for k, a in arrays.items():
            if k != NPC_KEY or replace_member is None:
                _write_npy_member(zf, k, a.shape, a.dtype.str, a.tobytes())
        if replace_member is not None:
            replace_member(zf)
    return arrays


_CHILD = """
import json, sys
from pathlib import Path
sys.path.insert(0, {tests!r})
from fixtures.corpora import TEST_OPTIONS
from marionette.ingest import discover, ingest_sample
ref = discover(Path({src!r}))[0]
r = ingest_sample(ref, Path({corpus!r}), TEST_OPTIONS)
# VmHWM is this program's own peak: ru_maxrss would also count the parent's pages shared before exec
hwm = next(int(x.split()[1]) for x in open("/proc/self/status") if x.startswith("VmHWM:"))
print(json.dumps({{"status": r.status, "reason": r.reason, "peak_rss_kb": hwm}}))
"""


def test_npz_that_would_inflate_to_1gb_is_quarantined_unread(synth_source, tmp_path):
    part = _copy_part(synth_source, tmp_path / "src", {"rec0000": "bomb"})
    npz = part / "bomb" / "skeleton.npz"
    joints = np.load(npz)[NPC_KEY].shape[1]
    inflated = 1 << 30
    frames = inflated // (joints * 3 * 4)
    _rewrite_npz(npz, lambda zf: _write_npy_member(zf, NPC_KEY, (frames, joints, 3), "<f4", frames * joints * 3 * 4))
    assert npz.stat().st_size < 8 << 20  # a few MB on disk, 1 GiB inflated
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            _CHILD.format(tests=str(Path(__file__).parent), src=str(tmp_path / "src"), corpus=str(tmp_path / "c")),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).parent.parent,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["status"] == "quarantined"
    reason = r["reason"]
    assert str(npz) in reason and f"{NPC_KEY}.npy" in reason and f"({frames}, {joints}, 3)" in reason, reason
    assert f"{frames * joints * 12:,} bytes" in reason and "not inflated" in reason, reason
    assert r["peak_rss_kb"] * 1024 < 400e6, f"peak RSS {r['peak_rss_kb'] / 1024:.0f} MB while refusing a 1 GiB member"


def test_member_over_the_configured_cap_is_quarantined(synth_source, tmp_path):
    _copy_part(synth_source, tmp_path / "src", {"rec0000": "big"})
    cap = 100_000  # below the hunter's and the drake's members (129,600 and 230,400 bytes)
    report = build_corpus(
        tmp_path / "src", tmp_path / "c", replace(TEST_OPTIONS, max_member_bytes=cap), workers=1, progress=False
    )
    (r,) = report["results"]
    assert r["status"] == "quarantined", r
    assert "skeleton.npz: member " in r["reason"] and ".npy declares shape (300, " in r["reason"], r["reason"]
    assert f"over the per-member cap of {cap:,} bytes" in r["reason"], r["reason"]
    report = build_corpus(tmp_path / "src", tmp_path / "c2", TEST_OPTIONS, workers=1, progress=False)
    assert [r["status"] for r in report["results"]] == ["ingested"]  # the default cap admits it


def test_archive_checks_the_zip_directory_and_header_before_inflating(synth_source, tmp_path):
    src = synth_source / "data_part1" / "rec0000" / "skeleton.npz"
    real = np.load(src)[NPC_KEY]
    cases = {
        # the header declares a small array, the zip directory 2 MiB more: over a 1 MiB cap, refused unread
        "directory": (
            lambda zf: _write_npy_member(zf, NPC_KEY, real.shape, "<f4", real.tobytes(), trailing=2 << 20),
            "the zip directory gives it 2,226,880 bytes uncompressed, over the per-member cap of 1,048,576 bytes",
        ),
        # bytes beyond what the header declares: not what numpy writes
        "trailing": (
            lambda zf: _write_npy_member(zf, NPC_KEY, real.shape, "<f4", real.tobytes(), trailing=100),
            "not an .npy file numpy wrote",
        ),
        "ints": (
            lambda zf: _write_npy_member(zf, NPC_KEY, real.shape, "<i4", real.astype("<i4").tobytes()),
            "expected a float (N, J, 3)",
        ),
        "joints": (lambda zf: _write_npy_member(zf, NPC_KEY, (4, 5000, 3), "<f4", 4 * 5000 * 12), "J ≤ 1024"),
        "frames": (
            lambda zf: _write_npy_member(zf, NPC_KEY, (400, real.shape[1], 3), "<f4", 400 * real.shape[1] * 12),
            "more than the 364 frames",
        ),
    }
    for name, (write, msg) in cases.items():
        p = tmp_path / f"{name}.npz"
        shutil.copy(src, p)
        _rewrite_npz(p, write)
        archive = SkeletonArchive(p, max_member_bytes=1 << 20)
        assert archive.keys == ["m1_25", "n1_0", "w1_3"]
        with pytest.raises(SampleError, match=re.escape(msg)) as ei:
            archive.read(NPC_KEY, max_frames=300 + 64)
        assert str(p) in str(ei.value) and f"{NPC_KEY}.npy" in str(ei.value), ei.value
    # an untouched member reads back exactly
    p = tmp_path / "good.npz"
    shutil.copy(src, p)
    np.testing.assert_array_equal(SkeletonArchive(p).read(NPC_KEY, max_frames=300), real)
    # a corrupt deflate stream is a clear error too
    data = bytearray(src.read_bytes())
    info = zipfile.ZipFile(src).getinfo(f"{NPC_KEY}.npy")
    mid = info.header_offset + 30 + len(info.filename) + len(info.extra) + info.compress_size // 2
    data[mid : mid + 64] = bytes(64)
    (tmp_path / "corrupt.npz").write_bytes(bytes(data))
    with pytest.raises(SampleError, match="unreadable, truncated or corrupt") as ei:
        SkeletonArchive(tmp_path / "corrupt.npz").read(NPC_KEY)
    assert "corrupt.npz" in str(ei.value) and NPC_KEY in str(ei.value)


def test_trn2_size_is_checked_before_the_body_is_read(tmp_path):
    good = Chunk.empty(3, -2, 2).to_bytes()
    big = tmp_path / "chunk_3_-2.trn2"
    big.write_bytes(good)
    os.truncate(big, 1_500_000_000)  # sparse: a 1.5 GB file that costs no disk
    tracemalloc.start()
    try:
        with pytest.raises(TerrainFormatError, match="trailing bytes: 1500000000 bytes, expected 480032") as ei:
            read_chunk(big)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(big) in str(ei.value)
    assert peak < 1 << 20, f"read_chunk allocated {peak:,} bytes before refusing the file"
    (tmp_path / "ok.trn2").write_bytes(good)
    assert read_chunk(tmp_path / "ok.trn2") == Chunk.empty(3, -2, 2)


def test_broken_depth_is_quarantined_at_ingest(synth_source, tmp_path):
    part = _copy_part(synth_source, tmp_path / "src", {"rec0000": "good", "rec0001": "garbage", "rec0002": "empty"})
    shutil.copytree(part / "good", part / "missing")
    shutil.copytree(part / "good", part / "short")
    (part / "garbage" / "depth.mkv").write_bytes(np.random.default_rng(0).integers(0, 256, 50_000, np.uint8).tobytes())
    (part / "empty" / "depth.mkv").write_bytes(b"")
    (part / "missing" / "depth.mkv").unlink()
    _reencode_first_frames(part / "good" / "depth.mkv", part / "short" / "depth.mkv", 100)
    report = build_corpus(tmp_path / "src", tmp_path / "c", TEST_OPTIONS, workers=1, progress=False)
    by = {r["sample"].split("/")[1]: r for r in report["results"]}
    assert by["good"]["status"] == "ingested"
    assert {k: v["status"] for k, v in by.items() if k != "good"} == dict.fromkeys(
        ("empty", "garbage", "missing", "short"), "quarantined"
    )
    for name in ("garbage", "empty"):
        assert by[name]["reason"].startswith(f"{part / name / 'depth.mkv'}: unreadable video"), by[name]["reason"]
    assert by["missing"]["reason"] == f"{part / 'missing' / 'depth.mkv'}: missing"
    short = by["short"]["reason"]
    assert short.startswith(f"{part / 'short'}: frame counts disagree") and "rgb.mp4 frames 300, depth.mkv frames 100" in short, (
        short
    )


def _reencode_first_frames(src: Path, dst: Path, n: int) -> None:
    import av

    with av.open(str(src)) as c:
        frames = [f.to_ndarray(format="gray") for _, f in zip(range(n), c.decode(video=0))]
    with av.open(str(dst), "w", format="matroska") as c:
        s = c.add_stream("ffv1", rate=30)
        s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], "gray"
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="gray")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_scan_reports_a_broken_depth_and_scans_and_renders_the_rest(corpus, synth_source, tmp_path):
    from marionette.pipeline import refresh

    src = tmp_path / "src"
    shutil.copytree(synth_source, src)
    c = tmp_path / "corpus"
    shutil.copytree(corpus, c)
    samples = pq.read_table(c / "meta" / "samples.parquet")
    moved = [str(src / Path(s).relative_to(synth_source.resolve())) for s in samples["source"].to_pylist()]
    pq.write_table(
        samples.set_column(samples.schema.get_field_index("source"), "source", pa.array(moved)), c / "meta" / "samples.parquet"
    )
    broken = Path(moved[1]) / "depth.mkv"
    broken.write_bytes(b"\x1aE\xdf\xa3 not a matroska file " * 100)  # broken after ingest
    done = refresh(c, scan_options=ScanOptions(frame_stride=10))  # what ingest and `terrain scan` run
    (stage,) = done.terrain.values()
    name = samples["sample"][1].as_py()
    assert list(stage["failed"]) == [name]
    assert str(broken) in stage["failed"][name], stage["failed"]
    assert sorted(r["sample"] for r in stage["scanned"]) == sorted(set(samples["sample"].to_pylist()) - {name})
    assert stage["chunks_written"]  # the other recordings' terrain was written
    assert done.pose["failed"] == {} and len(done.pose["rendered"]) == done.pose["chunks"] > 0  # every chunk rendered
    assert any(str(broken) in line for line in done.lines())  # the summary names the broken file
    again = scan_stages(c, options=ScanOptions(frame_stride=10), log=lambda *_: None)
    assert list(next(iter(again.values()))["failed"]) == [name]  # still reported on every rerun, never fatal


def _snapshot(root: Path) -> dict[str, tuple[int, bytes]]:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(root.rglob("*")) if p.is_file()}


def test_symlinks_out_of_the_source_tree_are_refused(synth_source, tmp_path):
    outside = tmp_path / "outside"
    _copy_part(synth_source, outside, {"rec0001": "elsewhere"})
    before = _snapshot(outside)
    part = _copy_part(synth_source, tmp_path / "src", {"rec0000": "good", "rec0002": "file_link"})
    (part / "dir_link").symlink_to(outside / "data_part1" / "elsewhere", target_is_directory=True)
    rgb = part / "file_link" / "rgb.mp4"
    rgb.unlink()
    rgb.symlink_to(outside / "data_part1" / "elsewhere" / "rgb.mp4")
    (part / "inside_link").symlink_to(part / "good", target_is_directory=True)  # stays inside: accepted
    report = build_corpus(tmp_path / "src", tmp_path / "c", TEST_OPTIONS, workers=1, progress=False)
    by = {r["sample"].split("/")[1]: r for r in report["results"]}
    assert by["good"]["status"] == "ingested" and by["inside_link"]["status"] == "ingested"
    target = (outside / "data_part1" / "elsewhere").resolve()
    assert by["dir_link"]["status"] == "quarantined"
    assert by["dir_link"]["reason"] == f"symlink leaves the source tree: {part / 'dir_link'} → {target}"
    assert by["file_link"]["status"] == "quarantined"
    assert by["file_link"]["reason"] == f"symlink leaves the source tree: {rgb} → {target / 'rgb.mp4'}"
    assert _snapshot(outside) == before
    rerun = build_corpus(tmp_path / "src", tmp_path / "c", TEST_OPTIONS, workers=1, progress=False)
    assert {r["sample"].split("/")[1]: r["status"] for r in rerun["results"]}["dir_link"] == "unchanged"


def test_discover_lists_what_it_skips(synth_source, tmp_path):
    root = tmp_path / "src"
    part = _copy_part(synth_source, root, {"rec0000": "good"})
    (part / ".hidden").mkdir()
    (part / "..name").mkdir()
    (part / "notes.txt").write_text("x")
    (part / "dangling").symlink_to(tmp_path / "nowhere")
    (root / "other").mkdir()
    (root / ".data_part9").mkdir()
    (root / "stages.json").write_text("{}")  # part of the layout: not listed
    skipped: list = []
    refs = discover(root, skipped)
    assert [r.name for r in refs] == ["data_part1/good"]
    got = {Path(p).relative_to(root).as_posix(): why for p, why in skipped}
    assert set(got) == {
        "data_part1/.hidden",
        "data_part1/..name",
        "data_part1/notes.txt",
        "data_part1/dangling",
        "other",
        ".data_part9",
    }
    assert got["data_part1/..name"].startswith("hidden name") and got[".data_part9"].startswith("hidden name")
    assert got["data_part1/notes.txt"].startswith("not a directory") and "broken symlink" in got["data_part1/dangling"]
    assert "data_part<x>" in got["other"]
    assert discover(root) == refs  # the list is optional
    one: list = []
    assert [r.name for r in discover(part, one)] == ["data_part1/good"]  # a part given directly
    assert {Path(p).name for p, _ in one} == {".hidden", "..name", "notes.txt", "dangling"}
