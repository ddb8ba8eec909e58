"""Stage directories from elsewhere: the upstream release's chunk naming opens read-only, imports into a corpus's
stage, and a missing, empty or foreign directory is an error naming it."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from marionette.bridge.targets import TerrainScene
from marionette.cli import main as cli
from marionette.corpus import Corpus
from marionette.corpus.paths import stage_dir
from terrain_scan.field import open_stage
from terrain_scan.scan import scan_stages
from terrain_scan.store import IMPORT_PREFIX, Stage, stage_terrain
from terrain_scan.trn2 import TerrainFormatError, read_chunk


def _upstream_copy(stage: Stage, out):
    """The stage's chunk files under the upstream release's names (``c_<cx>_<cz>.bin``, no manifest)."""
    out.mkdir()
    for name, (path, _) in stage.chunk_files().items():
        cx, cz = name.split("_")
        shutil.copyfile(path, out / f"c_{cx}_{cz}.bin")
    return out


def test_open_stage_of_a_missing_empty_or_foreign_directory_is_an_error(tmp_path):
    with pytest.raises(TerrainFormatError, match="no such stage directory") as e:
        open_stage(tmp_path / "nowhere")
    assert str(tmp_path / "nowhere") in str(e.value)
    (tmp_path / "empty" / "chunks").mkdir(parents=True)
    with pytest.raises(TerrainFormatError, match="no terrain chunk"):
        open_stage(tmp_path / "empty")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    for name in ("c_1_x.bin", "chunk_0_0.trn2", "notes.txt", "c_0_0.bin.tmp"):  # near misses of either naming
        (foreign / name).write_bytes(b"TRN2")
    with pytest.raises(TerrainFormatError, match="no terrain chunk"):
        open_stage(foreign)
    with pytest.raises(TerrainFormatError, match="no terrain chunk"):
        TerrainScene.of_stage(foreign)  # the bridge's terrain for `render --terrain DIR`, likewise


def test_upstream_chunks_open_read_only_and_stay_inside(scanned_corpus, tmp_path):
    c = Corpus(scanned_corpus)
    stage = stage_terrain(c.path, c.segments["stage"][0].as_py())
    up = _upstream_copy(stage, tmp_path / "upstream")
    ours, theirs = open_stage(stage.dir), open_stage(up)
    rng = np.random.default_rng(0)
    layers = stage.layers()[0]
    lo, hi = np.array([layers.gx.min(), layers.gz.min()]) - 5, np.array([layers.gx.max(), layers.gz.max()]) + 5
    x, z = rng.uniform(lo[0], hi[0], 20000), rng.uniform(lo[1], hi[1], 20000)
    ref = rng.uniform(layers.h.min() - 2, layers.h.max() + 2, 20000)
    a, b = ours.query(x, z, ref), theirs.query(x, z, ref)
    assert np.isfinite(a).mean() > 0.3
    np.testing.assert_array_equal(a, b)
    scene = TerrainScene.of_stage(up)
    assert len(scene.faces) == len(TerrainScene.of_stage(stage).faces) and scene.hashes == TerrainScene.of_stage(stage).hashes
    # both namings at once is ambiguous
    mixed = tmp_path / "mixed"
    shutil.copytree(stage.dir / "chunks", mixed / "chunks")
    next(iter(up.iterdir())).rename(mixed / next(iter(up.iterdir())).name)
    with pytest.raises(TerrainFormatError, match="both namings"):
        open_stage(mixed)
    # a chunk name that is a link out of the directory is refused, naming it
    outside = tmp_path / "elsewhere.bin"
    shutil.copyfile(next(iter(stage.chunk_files().values()))[0], outside)
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "c_0_0.bin").symlink_to(outside)
    with pytest.raises(TerrainFormatError, match="outside the stage directory"):
        open_stage(linked)


def test_import_reproduces_the_stage_and_survives_a_scan(corpus, scanned_corpus, tmp_path, capsys):
    scanned = Corpus(scanned_corpus)
    st = scanned.segments["stage"][0].as_py()
    source = stage_terrain(scanned.path, st)
    up = _upstream_copy(source, tmp_path / "upstream")
    work = tmp_path / "c"
    shutil.copytree(corpus, work)  # the same corpus, never scanned
    assert cli(["terrain", "import", str(up), str(work), "--stage", "nowhere", "--no-pose"]) != 0
    assert "no stage 'nowhere' (its stages: default)" in capsys.readouterr().err
    assert cli(["terrain", "import", str(up), str(work), "--stage", st, "--no-pose", "--quiet"]) == 0
    assert "import:upstream" in capsys.readouterr().out
    imported = stage_terrain(Corpus(work).path, st)
    # the scan's measured layers, merged and derived again (alias rule, hole fill), give its chunks: the same
    # layers and flags, hits and times; a hole-filled layer and a normal differ by float32 rounding (the scan filled from its
    # float64 heights, the import from the files' float32)
    assert imported.chunk_files().keys() == source.chunk_files().keys()
    for name, (path, _) in imported.chunk_files().items():
        a, b = read_chunk(path).cells, read_chunk(source.chunk_files()[name][0]).cells
        for k in ("flags", "hits", "ts"):
            assert np.array_equal(a[k], b[k]), (name, k)
        measured = (b["flags"] & 3) == 1
        assert np.array_equal(a["h"][measured], b["h"][measured])  # normals: renormalised, within an ulp (below)
        np.testing.assert_allclose(a["h"], b["h"], rtol=2e-7, atol=0)
        np.testing.assert_allclose(a["n"], b["n"], rtol=0, atol=2e-7)
    mtimes = {n: p.stat().st_mtime_ns for n, (p, _) in imported.chunk_files().items()}
    assert cli(["terrain", "import", str(up), str(work), "--stage", st, "--no-pose", "--quiet"]) == 0
    assert "already imported, unchanged" in capsys.readouterr().out
    assert {n: p.stat().st_mtime_ns for n, (p, _) in Stage(stage_dir(work, st)).chunk_files().items()} == mtimes
    # a scan of the corpus's recordings keeps the import beside them (it is no recording that left the corpus)
    copy = tmp_path / "scanned"
    shutil.copytree(scanned_corpus, copy)
    assert cli(["terrain", "import", str(up), str(copy), "--stage", st, "--name", "theirs", "--no-pose", "--quiet"]) == 0
    scan_stages(copy, st, incremental=True, log=lambda *_: None)
    names = set(Stage(stage_dir(copy, st)).recordings())
    assert IMPORT_PREFIX + "theirs" in names and len(names) == 1 + len(source.recordings())
    # the same terrain seen twice: the same measured layers, twice the hits
    both = Stage(stage_dir(copy, st))
    for name, (path, _) in both.chunk_files().items():
        a, b = read_chunk(path).cells, read_chunk(source.chunk_files()[name][0]).cells
        measured = (b["flags"] & 3) == 1
        assert np.array_equal(a["flags"], b["flags"]) and np.array_equal(a["h"][measured], b["h"][measured])
        assert np.array_equal(a["hits"][measured], np.minimum(2 * b["hits"][measured].astype(int), 65535))
