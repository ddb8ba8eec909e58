"""Scanning a corpus's stage: chunks written, incremental = full, re-scans change nothing."""

from __future__ import annotations

import os
import shutil

import numpy as np

from marionette.corpus.paths import stage_dir
from terrain_scan.scan import ScanOptions, corpus_stages, scan_stages
from terrain_scan.store import Stage
from terrain_scan.trn2 import read_chunk

FAST = ScanOptions(frame_stride=3)


def _files(d):
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted((d / "chunks").glob("*.trn2"))}


def test_scan_incremental_equals_full(corpus, tmp_path):
    work = tmp_path / "c"
    shutil.copytree(corpus, work)
    stages = corpus_stages(work)
    assert list(stages) == ["default"] and len(stages["default"]) == 3
    # incremental, one recording at a time (in reverse order), versus one full scan
    report = scan_stages(work, "default", incremental=True, options=FAST, log=lambda *_: None)
    sdir = stage_dir(work, "default")
    first = _files(sdir)
    assert first and len(report["default"]["scanned"]) == 3
    # scanning again changes nothing: no recording is read, no chunk is written
    again = scan_stages(work, "default", incremental=True, options=FAST, log=lambda *_: None)["default"]
    assert again["scanned"] == [] and again["chunks_written"] == [] and again["chunks_derived"] == [] and _files(sdir) == first
    # a full rescan reads everything and still writes nothing new, on two worker processes as in one
    full = scan_stages(work, "default", incremental=False, options=FAST, log=lambda *_: None, workers=2)["default"]
    assert len(full["scanned"]) == 3 and full["chunks_written"] == [] and _files(sdir) == first
    assert len(full["chunks_derived"]) >= len(first)  # a full scan derives every chunk
    here = report["default"]["scanned"][0]["worker"]  # one worker: scanned in this process
    assert here.endswith(f"/pid-{os.getpid()}") and all(s["worker"] != here for s in full["scanned"])  # then in the pool's
    # recordings added in another order give the same bytes
    other = tmp_path / "o"
    shutil.copytree(corpus, other)
    st = Stage(stage_dir(other, "default"))
    recs = {r["sample"]: r for r in corpus_stages(other)["default"]}
    src_stage = Stage(sdir)
    for name in sorted(recs, reverse=True):
        rec = src_stage.manifest["recordings"][name]
        with np.load(sdir / rec["file"], allow_pickle=False) as z:
            from terrain_scan.layers import Observations

            st.put(name, Observations(*(z[f] for f in Observations.FIELDS)), rec["input_hash"], rec["ts"])
        st.rebuild()
    assert {k: v[1] for k, v in _files(stage_dir(other, "default")).items()} == {k: v[1] for k, v in first.items()}
    # chunk contents are sane: finite, recording times from 2026, the stage ~1000 m from the origin
    for p in (sdir / "chunks").glob("*.trn2"):
        c = read_chunk(p)
        v = c.valid()
        assert np.isfinite(c.cells["h"][v]).all()
        assert (c.cells["ts"][v] >= 1767225600).all() or (c.cells["hits"][v] == 0).any()
        assert c.cx in (-10, -11) and c.cz in (8, 9)
