"""Directories published atomically (``io.atomic_dir``): a reader sees the old directory or the new one, never a
mix; a failed write leaves the old one and no temp directory; a second writer of the same content keeps the first."""

from __future__ import annotations

import stat

import pytest

from marionette.io import atomic_dir


def _tree(path) -> dict[str, bytes]:
    return {str(f.relative_to(path)): f.read_bytes() for f in sorted(path.rglob("*")) if f.is_file()}


def test_atomic_dir_publishes_a_new_directory_readable_by_others(tmp_path):
    out = tmp_path / "a" / "report"
    with atomic_dir(out) as tmp:
        assert tmp.parent == out.parent and not out.exists()
        (tmp / "sub").mkdir()
        (tmp / "sub" / "x.bin").write_bytes(b"x")
    assert _tree(out) == {"sub/x.bin": b"x"}
    assert stat.S_IMODE(out.stat().st_mode) == 0o755
    assert sorted(p.name for p in out.parent.iterdir()) == ["report"]


def test_atomic_dir_replaces_the_whole_previous_directory(tmp_path):
    out = tmp_path / "ckpt"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with atomic_dir(out) as tmp:
        (tmp / "new.txt").write_text("new")
    assert _tree(out) == {"new.txt": b"new"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt"]


def test_atomic_dir_keep_leaves_what_another_writer_published(tmp_path):
    out = tmp_path / "cache"
    with atomic_dir(out, exists="keep") as tmp:
        (tmp / "a.npy").write_bytes(b"first")
    with atomic_dir(out, exists="keep") as tmp:
        (tmp / "a.npy").write_bytes(b"second")
    assert _tree(out) == {"a.npy": b"first"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache"]


def test_atomic_dir_failure_leaves_the_old_directory_and_no_temp(tmp_path):
    out = tmp_path / "report"
    out.mkdir()
    (out / "report.json").write_text("{}")
    with pytest.raises(RuntimeError, match="plot failed"), atomic_dir(out) as tmp:
        (tmp / "report.json").write_text('{"half": true}')
        raise RuntimeError("plot failed")
    assert _tree(out) == {"report.json": b"{}"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_atomic_dir_refuses_a_file_in_the_way_and_an_unknown_mode(tmp_path):
    out = tmp_path / "x"
    out.write_text("a file")
    with pytest.raises(OSError), atomic_dir(out) as tmp:
        (tmp / "y").write_text("y")
    assert out.read_text() == "a file" and sorted(p.name for p in tmp_path.iterdir()) == ["x"]
    with pytest.raises(ValueError, match="exists must be"), atomic_dir(tmp_path / "z", exists="merge"):
        pass


def test_publish_new_names_a_file_only_where_the_name_is_free(tmp_path):
    from marionette.io import publish_new

    (tmp_path / "a.tmp").write_bytes(b"new")
    publish_new(tmp_path / "a.tmp", tmp_path / "a.arrow")
    assert (tmp_path / "a.arrow").read_bytes() == b"new" and not (tmp_path / "a.tmp").exists()
    (tmp_path / "b.tmp").write_bytes(b"second")
    with pytest.raises(FileExistsError, match="a.arrow"):
        publish_new(tmp_path / "b.tmp", tmp_path / "a.arrow")
    assert (tmp_path / "a.arrow").read_bytes() == b"new" and not (tmp_path / "b.tmp").exists()


def test_a_special_file_is_refused_by_name_without_a_blocking_read(tmp_path):
    import os

    from marionette.io import read_bounded, read_ipc, read_json

    fifo = tmp_path / "info.json"
    os.mkfifo(fifo)  # a read would wait for a writer forever
    with pytest.raises(ValueError, match="info.json: a FIFO, not a regular file"):
        read_json(fifo)
    zero = tmp_path / "stages.json"
    zero.symlink_to("/dev/zero")  # a read would never end
    with pytest.raises(ValueError, match="stages.json: a character device"):
        read_json(zero)
    with pytest.raises(ValueError, match="a directory"):
        read_bounded(tmp_path, 10)
    with pytest.raises(ValueError, match="a FIFO"):
        read_ipc(fifo)


def test_a_bounded_read_stops_at_its_limit_and_json_nesting_is_bounded(tmp_path):
    from marionette.io import json_depth, read_bounded, read_json

    big = tmp_path / "meta.json"
    big.write_bytes(b"[" + b"0," * 5000 + b"0]")
    assert len(read_bounded(big, 1 << 20)) == big.stat().st_size
    with pytest.raises(ValueError, match="meta.json: over the 1000-byte limit"):
        read_bounded(big, 1000)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 3000 + "]" * 3000)  # past what the parser could recurse into
    with pytest.raises(ValueError, match="deep.json: JSON nested 3000 deep"):
        read_json(deep)
    assert json_depth('{"a": [1, {"b": "[[[\\"]]"}]}') == 3 and read_json(big)[0] == 0


def test_every_reader_of_a_shard_chunk_video_or_archive_refuses_a_fifo_by_name(tmp_path):
    import os

    from marionette.bridge.gbuffer import read_gbuffer_meta
    from marionette.corpus.video_shards import PoseShard, member_index, read_at, read_chunks, read_members
    from marionette.recordings.errors import SampleError
    from marionette.recordings.skeleton_archive import SkeletonArchive
    from marionette.recordings.wildworld import video_info
    from marionette.video import decode_frames
    from terrain_scan.trn2 import TerrainFormatError, read_chunk

    fifo = tmp_path / "shard-000000.tar"
    os.mkfifo(fifo)  # each of these would block on it for ever
    for read in (
        read_members,
        read_chunks,
        member_index,
        PoseShard,
        lambda p: read_at(p, 0, 1),
        read_gbuffer_meta,
        decode_frames,
    ):
        with pytest.raises(ValueError, match="shard-000000.tar: a FIFO, not a regular file"):
            read(fifo)
    for read in (video_info, SkeletonArchive):
        with pytest.raises(SampleError, match="a FIFO, not a regular file"):
            read(fifo)
    with pytest.raises(TerrainFormatError, match="a FIFO, not a regular file"):
        read_chunk(fifo)
