"""Scanning a corpus's stage: chunks written, incremental = full, re-scans change nothing."""

from __future__ import annotations

import os
import shutil

import numpy as np

from marionette.corpus.paths import stage_dir
from terrain_scan.options import ScanOptions
from terrain_scan.scan import corpus_stages, scan_stages
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


def test_scan_options_are_checked_kept_and_shown(corpus, tmp_path, capsys):
    """Every scan knob reaches a user (flags, a JSON file, --scan-option), is checked where it is parsed, and the
    corpus keeps what its last scan used: a later scan with no options (ingest's, the flows') rescans nothing."""
    import json

    import pytest

    from marionette.cli import main as cli
    from marionette.commands.summary import inspect_text

    with pytest.raises(ValueError, match="max_depth_m must be a number > 0"):
        ScanOptions.from_json({"max_depth_m": -1.0})
    with pytest.raises(ValueError, match=r"unknown scan option\(s\) \['max_depth'\]"):
        ScanOptions.from_json({"max_depth": 30.0}, "x.json")
    with pytest.raises(ValueError, match="contact_hits must be an int ≥ 0"):
        ScanOptions(contact_hits=True)
    work = tmp_path / "c"
    shutil.copytree(corpus, work)
    assert "terrain  not scanned yet" in inspect_text(work)
    for bad, said in (("max_depth=3", "did you mean max_depth_m?"), ("edge_m=0.7", "edge_m must be a number in (0, 0.5)")):
        with pytest.raises(SystemExit) as exc:
            cli(["terrain", "scan", str(work), "--scan-option", bad])
        assert exc.value.code == 2 and said in capsys.readouterr().err
    (tmp_path / "scan.json").write_text(json.dumps({"contact_hits": 2, "mask_margin_m": 0.25}))
    args = ["terrain", "scan", str(work), "--no-pose", "--frame-stride", "10", "--scan-config", str(tmp_path / "scan.json")]
    assert cli([*args, "--scan-option", "max_depth_m=15", "--scan-option", "alias_support=8"]) == 0
    out = capsys.readouterr().out
    assert "scanning with frame_stride=10, max_depth_m=15.0, mask_margin_m=0.25, contact_hits=2, alias_support=8" in out
    kept = ScanOptions.stored(work)
    assert (kept.frame_stride, kept.max_depth_m, kept.contact_hits, kept.alias_support) == (10, 15.0, 2, 8)
    st = Stage(stage_dir(work, "default"))
    assert st.manifest["rebuilt"]["alias"] == [0.25, 5, 8] and len(st.recordings()) == 3
    assert "scanned with frame_stride=10, max_depth_m=15.0" in inspect_text(work)
    # a scan with no options uses the kept ones: nothing to rescan
    again = scan_stages(work, log=lambda *_: None)["default"]
    assert again["scanned"] == [] and len(again["unchanged"]) == 3 and again["chunks_derived"] == []
    # another depth range is another scan of every recording
    other = scan_stages(work, options=kept.updated(max_depth_m=12.0), log=lambda *_: None)["default"]
    assert len(other["scanned"]) == 3 and not other["failed"] and ScanOptions.stored(work).max_depth_m == 12.0
