"""Crash windows in finalize, transient failures, name collisions, cache invalidation, exact segments,
and the intrinsics of a real crop."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from fixtures.corpora import TEST_OPTIONS

from marionette.corpus import Corpus
from marionette.corpus.lock import corpus_lock
from marionette.ingest import build_corpus, finalize
from marionette.ingest import sample as sample_mod
from marionette.ingest.sample import valid_runs
from marionette.synth import load_truth
from marionette.video import CropResize


def _copy_part(src: Path, dst: Path, names: dict[str, str]) -> None:
    """Copy recordings of the session source into ``dst`` under new names."""
    part = dst / "data_part1"
    part.mkdir(parents=True, exist_ok=True)
    shutil.copy(src / "data_part1" / "skeleton_edges.json", part)
    for old, new in names.items():
        shutil.copytree(src / "data_part1" / old, part / new)


def _snapshot(corpus: Path) -> dict:
    c = Corpus(corpus)
    files = {f"{d}/{p.name}": p.read_bytes() for d in ("state", "video") for p in sorted((corpus / d).glob("*"))}
    return {"files": files, "segments": c.segments.drop(["stage"]).to_pylist(), "vocab": c.vocab, "stats": c.stats}


def test_segments_are_exactly_the_valid_runs(corpus, synth_source):
    c = Corpus(corpus)
    for sample in sorted(set(c.segments["sample"].to_pylist())):
        part, sid = sample.split("/")
        t = load_truth(synth_source, part, sid)
        want = valid_runs(np.asarray(t["monster_present"]) & np.asarray(t["camera_valid"]), TEST_OPTIONS.min_segment_frames)
        rows = [r for r in c.segments.to_pylist() if r["sample"] == sample]
        assert [(r["start"], r["stop"]) for r in rows] == want


def test_crash_inside_finalize_then_changed_source(synth_source, tmp_path, monkeypatch):
    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "rec0000", "rec0001": "rec0001"})
    corpus, reference = tmp_path / "corpus", tmp_path / "reference"
    build_corpus(src, reference, TEST_OPTIONS, workers=1, progress=False)  # the same history, no crash
    real_replace, moves = os.replace, []

    def crash_on_second_move(a, b):
        if "/staging/" in str(a) and not Path(a).name.startswith("."):
            moves.append(a)
            if len(moves) == 2:
                raise KeyboardInterrupt("simulated crash between two renames of finalize")
        real_replace(a, b)

    monkeypatch.setattr(os, "replace", crash_on_second_move)
    with pytest.raises(KeyboardInterrupt):
        build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    monkeypatch.setattr(os, "replace", real_replace)
    assert (corpus / "meta" / "finalize-plan.json").exists()
    # the source changes before the rerun: a recording is added, one of the planned ones breaks
    _copy_part(synth_source, tmp_path / "extra", {"rec0002": "rec0002"})
    shutil.copytree(tmp_path / "extra" / "data_part1" / "rec0002", src / "data_part1" / "rec0002")
    (src / "data_part1" / "rec0000" / "rgb.mp4").unlink()
    build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    build_corpus(src, reference, TEST_OPTIONS, workers=1, progress=False)
    assert _snapshot(corpus) == _snapshot(reference)
    assert Corpus(corpus).info.total_ingested == 2 and Corpus(corpus).info.total_quarantined == 1
    assert not (corpus / "meta" / "finalize-plan.json").exists()
    assert not (corpus / "staging").exists() or not list((corpus / "staging").iterdir())


def test_transient_failure_is_retried_on_the_next_run(synth_source, tmp_path, monkeypatch):
    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "rec0000"})
    corpus = tmp_path / "corpus"
    real = sample_mod.write_video_shard

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sample_mod, "write_video_shard", disk_full)
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    assert report["results"][0]["status"] == "quarantined" and "No space left" in report["results"][0]["reason"]
    monkeypatch.setattr(sample_mod, "write_video_shard", real)
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    assert report["results"][0]["status"] == "ingested"
    assert Corpus(corpus).info.total_quarantined == 0


def test_unreadable_input_is_quarantined_not_fatal(synth_source, tmp_path):
    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "good", "rec0001": "dir_npz"})
    npz = src / "data_part1" / "dir_npz" / "skeleton.npz"
    npz.unlink()
    npz.mkdir()
    report = build_corpus(src, tmp_path / "corpus", TEST_OPTIONS, workers=1, progress=False)
    by = {r["sample"].split("/")[1]: r for r in report["results"]}
    assert by["good"]["status"] == "ingested"
    assert by["dir_npz"]["status"] == "quarantined" and "skeleton.npz" in by["dir_npz"]["reason"]


def test_names_that_sanitise_alike_stay_distinct(synth_source, tmp_path):
    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "rec.1", "rec0001": "rec-1"})
    corpus = tmp_path / "corpus"
    build_corpus(src, corpus, TEST_OPTIONS, workers=2, progress=False)
    c = Corpus(corpus)
    assert c.info.total_ingested == 2 and len(c.shard_ids()) == 2
    segs = c.segments["segment"].to_pylist()
    assert len(segs) == len(set(segs)) and all("." not in s for s in segs)
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    assert {r["status"] for r in report["results"]} == {"unchanged"}


def test_edges_in_another_joint_order_are_rejected(synth_source, tmp_path):
    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "rec0000"})
    edges_path = src / "data_part1" / "skeleton_edges.json"
    edges = json.loads(edges_path.read_text())
    edges["npc"] = [[c, p] if i == 3 else [p, c] for i, (p, c) in enumerate(edges["npc"])]
    edges_path.write_text(json.dumps(edges))
    report = build_corpus(src, tmp_path / "corpus", TEST_OPTIONS, workers=1, progress=False)
    r = report["results"][0]
    assert r["status"] == "quarantined" and "skeleton_edges.json" in r["reason"] and "'npc'" in r["reason"]


def test_dynamics_view_is_recomputed_when_its_shard_changes(synth_source, tmp_path):
    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "rec0000"})
    corpus = tmp_path / "corpus"
    build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    c = Corpus(corpus)
    shard = c.shard_ids()[0]
    first = c.dynamics_shard(shard)
    cached = sorted(c.dynamics_dir().glob("*.arrow"))
    assert len(cached) == 1
    stamp = cached[0].stat().st_mtime_ns
    assert Corpus(corpus).dynamics_shard(shard).equals(first)  # served from the cache, not rewritten
    assert sorted(c.dynamics_dir().glob("*.arrow")) == cached and cached[0].stat().st_mtime_ns == stamp
    # the recording is re-exported with a change: the view follows, the stale file goes
    csv_path = src / "data_part1" / "rec0000" / "state.csv"
    lines = csv_path.read_text().splitlines(keepends=True)
    csv_path.write_text("".join(lines[:-40]))
    for name in ("skeleton.npz",):
        with np.load(src / "data_part1" / "rec0000" / name, allow_pickle=False) as z:
            arrays = {k: z[k][:-40] for k in z.files}
        np.savez(src / "data_part1" / "rec0000" / name, **arrays)
    import av

    from marionette.video import decode_frames, encode_mp4

    frames = np.stack(decode_frames(src / "data_part1" / "rec0000" / "rgb.mp4")[:-40])
    (src / "data_part1" / "rec0000" / "rgb.mp4").write_bytes(encode_mp4(frames, 30, TEST_OPTIONS.video))
    assert av  # PyAV wrote the shortened video
    depth = src / "data_part1" / "rec0000" / "depth.mkv"
    with av.open(str(depth)) as c:
        codes = [f.to_ndarray(format="gray") for f in c.decode(video=0)][:-40]
    with av.open(str(depth), "w", format="matroska") as c:
        s = c.add_stream("ffv1", rate=30)
        s.width, s.height, s.pix_fmt = codes[0].shape[1], codes[0].shape[0], "gray"
        for f in codes:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="gray")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    c2 = Corpus(corpus)
    again = c2.dynamics_shard(shard)
    assert again.num_rows < first.num_rows
    assert len(list(c2.dynamics_dir().glob("*.arrow"))) == 1


def test_second_build_on_a_locked_corpus_fails_fast(tmp_path, synth_source):
    corpus = tmp_path / "corpus"
    with corpus_lock(corpus), pytest.raises(RuntimeError, match="another build"):
        build_corpus(synth_source, corpus, TEST_OPTIONS, workers=1, progress=False)


def test_finalize_discards_samples_staged_with_other_options(synth_source, tmp_path):
    from dataclasses import replace

    src = tmp_path / "src"
    _copy_part(synth_source, src, {"rec0000": "rec0000"})
    corpus = tmp_path / "corpus"
    from marionette.ingest import discover, ingest_sample

    ingest_sample(discover(src)[0], corpus, replace(TEST_OPTIONS, min_segment_frames=40))
    info = finalize(corpus, TEST_OPTIONS)
    assert info["total_samples"] == 0 and not list((corpus / "staging").iterdir())


def test_intrinsics_follow_a_real_crop():
    cr = CropResize.fit(720, 1280, 176, 320)  # 320/176 is wider than 1280/720: rows are cropped
    assert (cr.x0, cr.y0, cr.w, cr.h) == (0, 8, 1280, 704)
    K = np.array([900.0, 900.0, 640.0, 360.0])
    rng = np.random.default_rng(0)
    pts = rng.uniform([-3, -2, 5], [3, 2, 30], (100, 3))  # camera frame, +Z forward for the pinhole
    u = K[0] * pts[:, 0] / pts[:, 2] + K[2]
    v = K[1] * pts[:, 1] / pts[:, 2] + K[3]
    K2 = cr.intrinsics(K)
    u2 = K2[0] * pts[:, 0] / pts[:, 2] + K2[2]
    v2 = K2[1] * pts[:, 1] / pts[:, 2] + K2[3]
    np.testing.assert_allclose(u2, (u - cr.x0) * 320 / cr.w, atol=1e-9)
    np.testing.assert_allclose(v2, (v - cr.y0) * 176 / cr.h, atol=1e-9)
    tall = CropResize.fit(1000, 500, 176, 320)  # taller source: rows are cropped
    assert tall.w == 500 and tall.x0 == 0 and tall.y0 == (1000 - tall.h) // 2 and tall.h == 275
