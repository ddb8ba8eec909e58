"""Keys are injective: two different sources never share a sample key, a segment id or a stage directory; names are
printed with their control characters escaped; a stage map from a source tree is checked before it is used."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from marionette.corpus import paths
from marionette.corpus.paths import ID_PATTERN
from marionette.corpus.stages import check_stage_map, is_recording_id
from marionette.ingest import check_keys, load_stage_map
from marionette.ingest.sample import safe_name, sample_key, segment_id
from marionette.io import printable
from marionette.recordings.wildworld import SampleRef
from marionette.schema import FIELD_RANGES

# A directory name: any characters but "/" and NUL; underscores, dashes and dots often, to make look-alikes likely.
NAMES = st.text(st.sampled_from("ab_-._") | st.characters(exclude_characters="/\x00"), min_size=1, max_size=80)
# the suite's examples are drawn the same way every run (derandomized); MARIONETTE_FUZZ_EXAMPLES=5000 searches afresh
EXAMPLES = int(os.environ.get("MARIONETTE_FUZZ_EXAMPLES", "300"))
FUZZ = settings(max_examples=EXAMPLES, derandomize="MARIONETTE_FUZZ_EXAMPLES" not in os.environ, database=None, deadline=None)


def _ref(part: str, sample: str) -> SampleRef:
    return SampleRef(Path("/src"), part, sample)


@FUZZ
@given(NAMES, NAMES, NAMES, NAMES)
def test_two_different_sources_never_share_a_key_or_a_segment_id(p1, s1, p2, s2):
    a, b = _ref(p1, s1), _ref(p2, s2)
    for ref in (a, b):
        assert ID_PATTERN.fullmatch(sample_key(ref)) and ID_PATTERN.fullmatch(segment_id(ref, 999))
    if (p1, s1) != (p2, s2):
        assert sample_key(a) != sample_key(b)
        assert segment_id(a, 0) != segment_id(b, 0)


def test_the_look_alikes_and_long_names_get_keys_of_their_own():
    a, b = _ref("data_part1", "x__y"), _ref("data_part1__x", "y")
    assert sample_key(a) != sample_key(b) and segment_id(a, 0) != segment_id(b, 0)
    c, d = _ref("data_part1", "x-y"), _ref("data_part1-x", "y")
    assert segment_id(c, 0) != segment_id(d, 0)
    assert safe_name("rec0000") == "rec0000" and safe_name("data_part1") == "data_part1"  # ordinary names are kept
    long = "L" * 250
    assert len(safe_name(long)) <= 64 and safe_name(long) != safe_name(long[:-1])
    assert check_keys([a, b, c, d]) == ([a, b, c, d], [])


def test_a_key_collision_refuses_both_by_name(monkeypatch):
    import marionette.ingest.sample as sample

    monkeypatch.setattr(sample, "safe_name", lambda s: "same")  # the hash collision safe_name makes all but impossible
    a, b, c = _ref("p", "one"), _ref("p", "two"), _ref("q", "x")
    kept, refused = check_keys([a, b])
    assert kept == [] and [p for p, _ in refused] == [str(a.path), str(b.path)]
    assert "p/two" in refused[0][1] and "p/one" in refused[1][1] and "both refused" in refused[0][1]
    assert check_keys([c]) == ([c], [])


@FUZZ
@given(st.text(max_size=40))
def test_printable_escapes_every_control_character(s):
    out = printable(s)
    assert out.isprintable()
    assert printable(out) == out


def test_printable_keeps_plain_names():
    assert printable("data_part1/rec0000: ok é ü") == "data_part1/rec0000: ok é ü"
    assert printable("bell\x07\x1b[2J") == "bell\\x07\\x1b[2J"


def test_field_ranges_name_the_first_value_outside():
    import numpy as np

    focal = FIELD_RANGES["focal"]
    assert focal.first_outside(np.array([[500.0, 500.0], [np.nan, np.nan], [0.0, 500.0]])) == (2, 0)
    assert focal.first_outside(np.array([[500.0, 1.0]])) is None
    assert FIELD_RANGES["position"].first_outside(np.array([[-3e38, 0.0, 0.0]])) == (0, 0)
    assert FIELD_RANGES["position"].first_outside(np.array([[-999_999.0, 5000.0, -5000.0]])) is None
    motion = FIELD_RANGES["motion_id"]
    assert motion.first_outside(np.array([-1.0, 999.0])) is None and motion.first_outside(np.array([1000.0])) == (0,)


def test_a_source_stage_map_is_checked_before_use(tmp_path):
    (tmp_path / "stages.json").write_text(json.dumps({"data_part1/rec0000": "arena", "data_part1/rec0001": "a.b"}))
    with pytest.raises(ValueError, match=r"stages\.json: recording 'data_part1/rec0001': stage 'a\.b' is not an id"):
        load_stage_map(tmp_path)
    (tmp_path / "stages.json").write_text(json.dumps({"../../etc/passwd": "arena"}))
    with pytest.raises(ValueError, match="is not a recording id"):
        load_stage_map(tmp_path)
    (tmp_path / "stages.json").write_text(json.dumps(["arena"]))
    with pytest.raises(ValueError, match="not an object"):
        load_stage_map(tmp_path)
    (tmp_path / "stages.json").write_text(json.dumps({f"data_part1/{'L' * 250}": "arena"}))
    assert load_stage_map(tmp_path) == {f"data_part1/{'L' * 250}": "arena"}
    assert check_stage_map({"p/x": "s-1"}, "w") == {"p/x": "s-1"}
    assert not is_recording_id("p/..") and not is_recording_id("p/a/b") and not is_recording_id("p/" + "x" * 256)


def test_two_stage_ids_never_share_a_directory(tmp_path):
    assert paths.stage_dir(tmp_path, "arena").name == "stage_arena"
    for bad in ("a.b", "a b", "../x", ""):
        with pytest.raises(paths.CorpusPathError, match="stage id"):
            paths.stage_dir(tmp_path, bad)
