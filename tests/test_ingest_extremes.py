"""One bad value costs only its sample: values outside their declared ranges, names the file system allows but a key
would not, and two sources whose names read alike once joined, all in one ingest run."""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
from fixtures.corpora import TEST_OPTIONS

from marionette.corpus import Corpus
from marionette.ingest import build_corpus
from marionette.recordings.errors import SampleError
from marionette.recordings.wildworld import SampleRef
from marionette.schema import load_scene
from terrain_scan.accumulate import scan_recording
from terrain_scan.depth import DepthDecoder

pytestmark = pytest.mark.corpus

LONG = "L" * 250  # a sample directory name of 250 bytes: within the file system's 255


def _copy(synth: Path, src: Path, part: str, name: str, rec: str = "rec0000") -> Path:
    d = src / part
    d.mkdir(parents=True, exist_ok=True)
    if not (d / "skeleton_edges.json").exists():
        shutil.copy(synth / "data_part1" / "skeleton_edges.json", d)
    shutil.copytree(synth / "data_part1" / rec, d / name)
    return d / name


def _set_joint(d: Path, value: float) -> None:
    z = dict(np.load(d / "skeleton.npz"))
    key = next(k for k in z if k.startswith("m"))
    a = z[key].astype(np.float64)
    a[40, 3, 1] = value
    z[key] = a
    np.savez(d / "skeleton.npz", **z)


def _set_cell(d: Path, column: str, row: int, value: str) -> None:
    rows = list(csv.reader(io.StringIO((d / "state.csv").read_text())))
    rows[row][rows[0].index(column)] = value
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    (d / "state.csv").write_text(out.getvalue())


def _depth_video(path: Path, height: int, width: int, frames: int = 2) -> None:
    """A gray depth video of ``frames`` frames of another size than its sample's RGB."""
    path.unlink()
    with av.open(str(path), "w") as out:
        s = out.add_stream("ffv1", rate=30)
        s.width, s.height, s.pix_fmt = width, height, "gray"
        for i in range(frames):
            frame = av.VideoFrame.from_ndarray(np.full((height, width), 40 + i % 200, np.uint8), format="gray")
            out.mux(s.encode(frame))
        out.mux(s.encode())


def test_a_depth_video_of_another_size_is_refused_from_its_headers_by_the_scan(synth_source, tmp_path):
    d = _copy(synth_source, tmp_path / "src", "data_part1", "swapped")
    _depth_video(d / "depth.mkv", 180, 320, frames=300)
    with pytest.raises(SampleError, match=r"depth\.mkv: 320×180 frames; rgb\.mp4's are 160×90"):
        scan_recording(SampleRef(tmp_path / "src", "data_part1", "swapped"), load_scene("duel"), DepthDecoder())


def test_each_bad_value_costs_only_its_sample_and_every_name_gets_a_key_of_its_own(synth_source, tmp_path):
    src = tmp_path / "src"
    _copy(synth_source, src, "data_part1", "good")
    _set_joint(_copy(synth_source, src, "data_part1", "huge_joint"), 1e308)
    _set_joint(_copy(synth_source, src, "data_part1", "big_joint"), -3e38)
    _set_cell(_copy(synth_source, src, "data_part1", "id_past_int32"), "monster.list.0.motion_id", 30, "3000000000")
    _set_cell(_copy(synth_source, src, "data_part1", "fx_zero"), "camera.K", 12, "(0.0, 77.9, 80.0, 45.0)")
    _set_cell(_copy(synth_source, src, "data_part1", "hp_huge"), "npc.list.0.hp", 7, "1e308")
    _copy(synth_source, src, "data_part1", LONG, "rec0001")
    _copy(synth_source, src, "data_part1", "x__y", "rec0001")  # reads as part "data_part1__x", sample "y" once joined
    _copy(synth_source, src, "data_part1__x", "y", "rec0002")
    _copy(synth_source, src, "data_part1", "bell\x07\x1b[2Jname", "rec0002")  # control characters in a name
    _depth_video(_copy(synth_source, src, "data_part1", "depth_huge") / "depth.mkv", 4608, 8192)
    fifo = _copy(synth_source, src, "data_part1", "fifo_rgb") / "rgb.mp4"
    fifo.unlink()
    os.mkfifo(fifo)  # a read of it would block the build forever

    corpus = tmp_path / "corpus"
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=2, progress=False)
    status = {r["sample"]: r for r in report["results"]}
    reasons = {k.split("/")[1]: v["reason"] for k, v in status.items() if v["status"] == "quarantined"}
    assert set(reasons) == {"huge_joint", "big_joint", "id_past_int32", "fx_zero", "hp_huge", "depth_huge", "fifo_rgb"}, reasons
    for name, what in (
        ("huge_joint", "skeleton.npz: key 'm1_25': frame 40, joint 3: 1e+308 is outside the position range"),
        ("big_joint", "skeleton.npz: key 'm1_25': frame 40, joint 3: -3e+38 is outside the position range"),
        ("id_past_int32", "state.csv: row 30, column 'monster.list.0.motion_id': 3e+09 is outside the motion_id range"),
        ("fx_zero", "state.csv: row 12, column 'camera.K': 0 is outside the focal range"),
        ("hp_huge", "state.csv: row 7, column 'npc.list.0.hp': 1e+308 is outside the hp range"),
        ("depth_huge", "depth.mkv: 8192×4608 frames; rgb.mp4's are 160×90"),
        ("fifo_rgb", "rgb.mp4: a FIFO, not a regular file"),
    ):
        assert name in reasons[name] and what in reasons[name], reasons[name]
    ingested = {k for k, v in status.items() if v["status"] == "ingested"}
    assert ingested == {
        "data_part1/good",
        f"data_part1/{LONG}",
        "data_part1/x__y",
        "data_part1__x/y",
        "data_part1/bell\x07\x1b[2Jname",
    }
    assert report["skipped"] == []

    c = Corpus(corpus)
    records = {r["sample"]: r for r in c.samples.to_pylist()}
    assert set(records) == set(status)  # one record per sample: the look-alikes were not merged
    keys = {p.stem for p in (corpus / "meta" / "samples").glob("*.json")}
    assert len(keys) == len(records) and all(len(k) <= 200 for k in keys)
    segments = c.segments.to_pylist()
    by_sample: dict[str, set[str]] = {}
    for s in segments:
        by_sample.setdefault(s["sample"], set()).add(s["segment"])
    assert set(by_sample) == ingested
    assert sum(len(v) for v in by_sample.values()) == len({s["segment"] for s in segments})  # segment ids are distinct
    assert all(len(s) <= 200 for v in by_sample.values() for s in v)
    quarantine = {
        r["sample"].split("/")[1]: r["reason"] for r in pq.read_table(corpus / "meta" / "quarantine.parquet").to_pylist()
    }
    assert quarantine == reasons
    info = c.info
    assert (info.total_samples, info.total_ingested, info.total_quarantined) == (len(records), len(ingested), len(reasons))
    assert info.total_frames == sum(s["frames"] for s in segments)


def test_a_recording_committed_under_another_key_is_held_once(synth_source, tmp_path):
    """A corpus whose record of a recording carries a key another version's naming made: the next ingest commits the
    recording under today's key and drops the other record and its shard, so the recording is never held twice."""
    src = tmp_path / "src"
    _copy(synth_source, src, "data_part1", "rec0000")
    corpus = tmp_path / "corpus"
    build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    samples = corpus / "meta" / "samples"
    (record,) = samples.glob("*.json")
    rec = json.loads(record.read_text())
    old_shard = corpus / "state" / f"shard-{rec['shard']:06d}.arrow"
    rec["key"] = "data_part1__rec0000--0123456789ab"  # as an older naming would have keyed it
    record.unlink()
    (samples / f"{rec['key']}.json").write_text(json.dumps(rec))
    build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    assert sorted(p.stem for p in samples.glob("*.json")) == ["data_part1__rec0000"]
    c = Corpus(corpus)
    assert c.samples["sample"].to_pylist() == ["data_part1/rec0000"]
    assert len(set(c.segments["segment"].to_pylist())) == c.segments.num_rows
    assert not old_shard.exists() and c.info.total_frames == sum(c.segments["frames"].to_pylist())
