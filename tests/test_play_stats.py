"""Recorded play statistics (marionette.corpus.play_stats) against the synthetic recordings' own truth."""

from __future__ import annotations

import numpy as np
import pytest

from marionette.corpus import Corpus
from marionette.corpus.play_stats import APPROACH_M, play_stats, play_stats_lines
from marionette.synth import load_truth
from marionette.synth.clips import CLIPS
from marionette.synth.sim import clip_at_frames, simulate


def _truth_segments(corpus: Corpus, source, split: str | None = None):
    """Per corpus segment: (truth, frames [start, stop)) from the recordings the corpus was built from."""
    for row in corpus.segments.to_pylist():
        if split is not None and row["split"] != split:
            continue
        part, sample = row["sample"].split("/")
        yield load_truth(source, part, sample), np.arange(row["start"], row["stop"])


def test_separation_matches_the_recorded_roots(corpus, synth_source):
    c = Corpus(corpus)
    stats = play_stats(c)
    assert stats.segments == len(c.segment_ids()) and stats.frames == c.info.total_frames
    all_d, after, ends = [], [], []
    for truth, frames in _truth_segments(c, synth_source):
        d = np.linalg.norm(truth["root_world"]["monster"][frames] - truth["root_world"]["hunter"][frames], axis=1)
        all_d.append(d)
        close = np.flatnonzero(d <= APPROACH_M)
        if len(close):
            after.append(d[close[0] :])
        ends.append(d[-1])
    (sep,) = stats.separation
    assert sep.pair == ("monster", "hunter") and sep.frames == sum(len(d) for d in all_d)
    assert sep.median_m == pytest.approx(np.median(np.concatenate(all_d)), abs=1e-4)
    assert sep.median_after_approach_m == pytest.approx(np.median(np.concatenate(after)), abs=1e-4)
    assert sep.median_at_segment_end_m == pytest.approx(np.median(ends), abs=1e-4)
    assert sep.median_horizontal_m <= sep.median_m + 1e-9


def test_class_mix_and_tokens(corpus, synth_source):
    c = Corpus(corpus)
    stats = play_stats(c)
    for entity in ("monster", "hunter"):
        share = stats.class_share[entity]
        assert sum(share.values()) == pytest.approx(1.0)
        # the recorded clip frame by frame (the game's truth), classed by the corpus's vocab
        key = next(k for k in c.vocab["entity_types"] if k.startswith({"monster": "drake", "hunter": "hunter"}[entity]))
        vocab_class = {a["composite"]: a["class"] for a in c.vocab["entity_types"][key]["actions"]}
        counts: dict[str, int] = {}
        for truth, frames in _truth_segments(c, synth_source):
            plan = simulate(truth["seed"], truth["index"], truth["n_frames"], float(truth["fps"]))
            names, _ = clip_at_frames(plan, entity, frames)
            for n in names:
                cls = vocab_class[CLIPS[entity][n].composite]
                counts[cls] = counts.get(cls, 0) + 1
        total = sum(counts.values())
        assert set(share) == set(counts), (entity, share, counts)
        for cls, n in counts.items():
            assert share[cls] == pytest.approx(n / total, abs=1e-9), (entity, cls, share, counts)
        t = stats.tokens[entity]
        assert t.vocab == c.vocab["entity_types"][key]["size"] - 1 == sum(t.vocab_per_class.values())
        assert t.used == t.vocab == sum(t.used_per_class.values())  # every token of a corpus's vocab was played in it
        assert 0 <= t.often <= t.vocab
    lines = play_stats_lines(stats)
    assert any(line.startswith("  separation monster–hunter: median ") for line in lines)
    assert sum(line.startswith("  classes ") for line in lines) == 2 and sum(line.startswith("  tokens ") for line in lines) == 2


def test_split_and_shard_limits(corpus):
    c = Corpus(corpus)
    split = sorted(set(c.segments["split"].to_pylist()))[0]
    part = play_stats(c, split=split)
    assert part.segments == len(c.segment_ids(split))
    one = play_stats(c, max_shards=1)
    assert one.shards_read == 1 and one.shards_total == len(c.shard_ids())
    assert one.segments == sum(r["shard"] == c.shard_ids()[0] for r in c.segments.to_pylist())
    assert "(first 1 of" in play_stats_lines(one)[0]
