"""Ingest on synthetic recordings: orientation, reconstruction, derived files, views, video shards."""

from __future__ import annotations

import json
import shutil
import tarfile

import numpy as np
import pyarrow.compute as pc
import pytest
from fixtures.corpora import SYNTH, TEST_OPTIONS

from marionette import geometry as geo
from marionette.commands.summary import inspect_text
from marionette.corpus import Corpus, world_of_rows
from marionette.ingest import build_corpus
from marionette.schema import SchemaError
from marionette.synth import generate, load_truth, world_skeletons_at
from marionette.video import decode_frames


def fixed_rows(col, w):
    return col.combine_chunks().values.to_numpy(zero_copy_only=False).reshape(-1, w)


def _segments(c: Corpus):
    for seg in c.segments.to_pylist():
        yield seg, c.read_segment(seg["segment"])


def test_corpus_shape(corpus):
    c = Corpus(corpus, expect="duel")
    info = c.info.to_json()
    assert info["layout"]["dim"] == 276 and info["layout"]["slices"]["weapon.points"] == [258, 264]
    assert info["features"]["state"]["shape"] == [276]
    assert info["total_ingested"] == SYNTH["recordings"] and info["total_quarantined"] == 0
    assert info["total_segments"] >= SYNTH["recordings"]  # absent-monster / bad-camera spans split them
    for seg in c.segments.to_pylist():
        assert "." not in seg["segment"]
    with pytest.raises(SchemaError, match="hunter_solo"):
        Corpus(corpus, expect="hunter_solo")


def test_rotation_matches_true_heading(corpus, synth_source):
    c = Corpus(corpus)
    L = c.layout
    checked = 0
    for seg, rows in _segments(c):
        part, sid = seg["sample"].split("/")
        truth = load_truth(synth_source, part, sid)
        frames = rows["frame"].to_numpy()
        state = fixed_rows(rows["state"], L.dim).astype(np.float64)
        for name in ("monster", "hunter"):
            R = geo.rot6d_to_matrix(state[:, L.slice(f"{name}.rot6d")])
            fwd = R @ np.asarray(L.entity(name).rig.forward_axis)
            heading = np.arctan2(fwd[:, 0], fwd[:, 2])
            err = np.angle(np.exp(1j * (heading - truth["heading"][name][frames])))
            assert np.abs(err).max() < 1e-3, (seg["segment"], name, np.abs(err).max())
            checked += len(frames)
    assert checked > 0


def test_reconstruction_equals_recorded_joints(corpus, synth_source):
    c = Corpus(corpus)
    L = c.layout
    for seg, rows in _segments(c):
        part, sid = seg["sample"].split("/")
        with np.load(synth_source / part / sid / "skeleton.npz", allow_pickle=False) as z:
            skel = {k: z[k] for k in z.files}
        state = fixed_rows(rows["state"], L.dim)
        frames = rows["frame"].to_numpy()
        anchors = {e.name: fixed_rows(rows[f"{e.name}.root_world"], 3)[0] for e in L.articulated}
        world = geo.state_to_world(L, state, anchors)
        types = {e.name: int(rows[f"{e.name}.type_id"][0].as_py()) for e in L.entities}
        for e in L.entities:
            rec = skel[f"{e.source_kind}{e.source_index}_{types[e.name]}"][frames][:, list(e.rig.keep_source_index)]
            err = np.abs(world[e.name]["joints"] - rec).max()
            assert err < 1e-4, (seg["segment"], e.name, err)
            assert np.abs(rec[:, 0, 0]).max() > 800  # the stage is ~1000 m from the origin


def _longest_runs(c: Corpus, entity: str) -> dict[int, int]:
    """Longest uninterrupted play of each composite action in the corpus, in frames."""
    best: dict[int, int] = {}
    for _, rows in _segments(c):
        act = rows[f"{entity}.action"].to_numpy()
        starts = np.flatnonzero(np.concatenate([[True], act[1:] != act[:-1]]))
        for s, e in zip(starts, np.concatenate([starts[1:], [len(act)]])):
            best[int(act[s])] = max(best.get(int(act[s]), 0), int(e - s))
    return best


def test_vocab_kinds_and_classes_match_truth(corpus, synth_source):
    c = Corpus(corpus)
    truth = load_truth(synth_source, "data_part1", "rec0000")
    compared = full = 0
    for etype, v in c.vocab["entity_types"].items():
        entity = "monster" if etype.startswith("drake") else "hunter"
        clips = {int(k): d for k, d in truth["clips"][entity].items()}
        runs = _longest_runs(c, entity)
        tokens = [a["token"] for a in v["actions"]]
        assert tokens == list(range(len(tokens)))
        for act in v["actions"][1:]:
            want = clips[act["composite"]]
            # clip length = largest motion_frame seen + 1: exact once a whole play was recorded
            assert act["clip_length"] <= want["length"], (etype, act, want)
            if runs[act["composite"]] >= want["length"]:
                assert act["clip_length"] == want["length"], (etype, act, want)
                full += 1
            # kind and class are read from the played motion: a loop that a segment's end stopped before it
            # wrapped reads as an event, so they are compared where a whole play (a loop: one cycle and a frame) was recorded
            if runs[act["composite"]] >= want["length"] + (want["kind"] == "state"):
                assert act["kind"] == want["kind"], (etype, act, want)
                assert act["class"] == want["class"], (etype, act, want)
                compared += 1
    assert compared >= 8 and full >= 6


def test_stats_are_finite_and_describe_train_rows(corpus):
    c = Corpus(corpus)
    st = c.stats["state"]
    assert len(st["mean"]) == 276 and np.isfinite(st["std"]).all()
    assert (np.asarray(st["min"]) <= np.asarray(st["mean"]) + 1e-6).all()
    assert st["count"] > 0


def test_dynamics_view_matches_analytic_motion(corpus, synth_source):
    c = Corpus(corpus)
    L = c.layout
    errs = []
    for seg in c.segments.to_pylist():
        view = c.dynamics_segment(seg["segment"])
        t = view["t"].to_numpy()
        assert np.allclose(np.diff(t), 1 / 20)
        part, sid = seg["sample"].split("/")
        truth = world_skeletons_at(synth_source, part, sid, t)
        world = world_of_rows(L, view)
        for e in L.entities:
            want = truth[e.name][:, list(e.rig.keep_source_index)]
            errs.append(np.linalg.norm(world[e.name] - want, axis=-1).ravel())
        # re-derived state: δ_0 = 0 and reconstruction from the view's own anchor
        state = fixed_rows(view["state"], L.dim)
        assert np.all(state[0, L.slice("hunter.root")] == 0)
        back = geo.state_to_world(L, state, {e.name: world[e.name][0, 0] for e in L.articulated})
        assert np.abs(back["hunter"]["joints"] - world["hunter"]).max() < 1e-4
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.005 and np.percentile(errs, 99) < 0.05, (np.median(errs), np.percentile(errs, 99))
    # cached: a second read comes from derived/
    assert list(c.dynamics_dir().glob("shard-*.arrow"))


def test_video_shards_are_webdataset_chunks(corpus):
    c = Corpus(corpus)
    seen = 0
    for shard in c.shard_ids():
        with tarfile.open(c.video_path(shard)) as tar:
            names = tar.getnames()
            keys = sorted({n.split(".", 1)[0] for n in names})
            for key in keys[:2]:
                assert "." not in key and "__c" in key
                meta = json.loads(tar.extractfile(f"{key}.json").read())
                frames = decode_frames(tar.extractfile(f"{key}.rgb.mp4").read())
                assert len(frames) == 81 == meta["frames"][1] - meta["frames"][0]
                assert frames[0].shape == (72, 128, 3)
                K = np.asarray(meta["K"])
                assert K.shape == (81, 4)
                # intrinsics after the crop/resize: the principal point stays centred
                np.testing.assert_allclose(K[:, 2:], np.broadcast_to([64.0, 36.0], (81, 2)), atol=0.5)
                seen += 1
    assert seen > 0


def test_inspect_lists_everything(corpus):
    text = inspect_text(corpus)
    for word in ("segments", "hours", "splits", "vocab", "drake", "hunter", "shards", "quarantine", "monster.rot6d"):
        assert word in text
    # the recorded play statistics (marionette.corpus.play_stats)
    for line in ("separation monster–hunter: median ", "classes monster: ", "classes hunter: ", "tokens hunter: "):
        assert f"\n  {line}" in text, line


def test_adding_a_recording_keeps_splits_and_shards(synth_source, tmp_path):
    src = tmp_path / "src"
    generate(src, **{**SYNTH, "recordings": 2, "seconds": 6.0})
    corpus = tmp_path / "corpus"
    build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    c1 = Corpus(corpus)
    before = {
        p.name: (p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted((corpus / "state").glob("*")) + sorted((corpus / "video").glob("*"))
    }
    splits1 = dict(zip(c1.segments["segment"].to_pylist(), c1.segments["split"].to_pylist()))
    # a rerun over the unchanged source does no ingest work
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    assert {r["status"] for r in report["results"]} == {"unchanged"}
    generate(src, **{**SYNTH, "recordings": 3, "seconds": 6.0})  # same seed: the first two are identical
    report = build_corpus(src, corpus, TEST_OPTIONS, workers=1, progress=False)
    assert sorted(r["status"] for r in report["results"]) == ["ingested", "unchanged", "unchanged"]
    c2 = Corpus(corpus)
    after = {
        p.name: (p.stat().st_mtime_ns, p.read_bytes())
        for p in sorted((corpus / "state").glob("*")) + sorted((corpus / "video").glob("*"))
    }
    for name, v in before.items():
        assert after[name] == v, f"{name} was rewritten"
    assert len(after) == len(before) + 2
    splits2 = dict(zip(c2.segments["segment"].to_pylist(), c2.segments["split"].to_pylist()))
    assert all(splits2[k] == v for k, v in splits1.items())
    assert len(set(c2.segments["segment"].to_pylist())) == c2.segments.num_rows


def test_slice_filter_skips_and_lists(synth_source, tmp_path):
    from dataclasses import replace

    corpus = tmp_path / "corpus"
    src = tmp_path / "src"
    shutil.copytree(
        synth_source / "data_part1",
        src / "data_part1",
        ignore=lambda d, names: [n for n in names if n not in ("rec0000", "skeleton_edges.json") and d.endswith("data_part1")],
    )
    build_corpus(src, corpus, replace(TEST_OPTIONS, monster_species=99), workers=1, progress=False)
    c = Corpus(corpus)
    rows = c.samples.to_pylist()
    assert [r["status"] for r in rows] == ["skipped"] and "99" in rows[0]["reason"]
    assert c.quarantine.num_rows == 0
    assert "skipped" in inspect_text(corpus)
    assert pc.sum(c.segments["frames"]).as_py() in (None, 0)


def test_hunter_only_scene_and_foreign_shards(synth_source, corpus, tmp_path):
    from dataclasses import replace

    solo = tmp_path / "solo"
    build_corpus(synth_source, solo, replace(TEST_OPTIONS, scene="hunter_solo"), workers=1, progress=False)
    cs = Corpus(solo, expect="hunter_solo")
    assert cs.info.layout["dim"] == 108 and "monster.root" not in cs.info.layout["slices"]
    # without the monster, its absent spans no longer break segments
    assert cs.info.total_frames > Corpus(corpus).info.total_frames
    # a duel corpus refuses hunter_solo samples, naming both layouts
    duel_copy = tmp_path / "duel"
    shutil.copytree(corpus, duel_copy)
    with pytest.raises(SchemaError, match="duel.*hunter_solo"):
        build_corpus(synth_source, duel_copy, replace(TEST_OPTIONS, scene="hunter_solo"), workers=1, progress=False)
    # a foreign shard dropped into a corpus is caught by the reader
    c = Corpus(duel_copy)
    shard = c.shard_ids()[0]
    shutil.copy(cs.state_path(cs.shard_ids()[0]), c.state_path(shard))
    with pytest.raises(SchemaError) as ei:
        c.read_shard(shard)
    assert "hunter_solo" in str(ei.value) and "duel" in str(ei.value) and f"shard-{shard:06d}" in str(ei.value)
